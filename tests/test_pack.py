"""Tests for sender.pack: quantised geometry reproduces the pre-quantisation geometry within
the quantisers' bounds, and clamping is flagged and counted."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.models.geometry import Pose, rotation_matrix, rotation_vector
from facewire.models.rig import Rig
from facewire.protocol.packet import PACKET_BYTES, QUANTISERS, Flag, PacketError
from facewire.sender.pack import pack, unpack_geometry

# Half steps of the quantisers (protocol.packet): rotation, shift_xy, shift_z, residuals.
ROT_DEG, SHIFT_XY, SHIFT_Z, RESIDUAL = (q.step / 2 for q in QUANTISERS[:4])


def test_decoded_geometry_within_bounds(rig: Rig) -> None:
    rng = np.random.default_rng(5)
    # worst-case landmark error from the residual quantisation: |B| row sums x the largest
    # 3D error of one point (two tangent coordinates off by half a step each)
    weights = np.abs(rig._landmark_weights).sum(axis=1)  # (68,)
    landmark_bound = weights * RESIDUAL * np.sqrt(2) + 1e-4
    for k in range(50):
        rvec = rng.uniform(-0.6, 0.6, 3)
        pose = Pose(rotation=rotation_matrix(rvec),
                    translation=np.array([rng.uniform(-100, 100), rng.uniform(-100, 100),
                                          rng.uniform(-1500, -300)]))
        uv = rng.uniform(-20, 20, (9, 2)).astype(np.float32)
        residuals = rig.from_tangent(uv)
        packed = pack(65530 + k, Flag.FACE_PRESENT, pose, uv)
        assert len(packed.packet) == PACKET_BYTES and packed.clamped == 0
        frame, got, decoded = unpack_geometry(rig, packed.packet)
        assert frame.seq == (65530 + k) % 65536 and frame.flags == Flag.FACE_PRESENT
        assert np.abs(np.degrees(rotation_vector(got.rotation) - rvec)).max() <= ROT_DEG + 1e-4
        err_t = np.abs(got.translation - pose.translation)
        assert err_t[:2].max() <= SHIFT_XY + 1e-4 and err_t[2] <= SHIFT_Z + 1e-3
        assert np.abs(frame.residuals - uv).max() <= RESIDUAL + 1e-5
        assert np.abs(packed.frame.residuals - uv).max() == 0  # carried as given, once
        err_d = np.linalg.norm(decoded - residuals, axis=1)
        assert err_d.max() <= RESIDUAL * np.sqrt(2) + 1e-5
        err_l = np.linalg.norm(rig.landmarks(decoded) - rig.landmarks(residuals), axis=1)
        assert np.all(err_l <= landmark_bound)


def test_clamping_is_flagged_and_counted(rig: Rig) -> None:
    pose = Pose(rotation=np.eye(3), translation=np.array([0.0, 0.0, -50.0]))  # too close
    uv = np.array([[40.0, 0.0]] + [[0.0, 0.0]] * 8, np.float32)
    packed = pack(0, Flag.FACE_PRESENT, pose, uv)
    assert packed.clamped == 2
    assert packed.frame.flags & Flag.CLAMPED
    frame, got, decoded = unpack_geometry(rig, packed.packet)
    assert frame.flags & Flag.CLAMPED
    assert got.translation[2] == -100.0
    assert frame.residuals[0, 0] == pytest.approx(31.75)
    ok = pack(1, Flag.FACE_PRESENT, Pose(np.eye(3), np.array([0.0, 0.0, -600.0])),
              np.zeros((9, 2), np.float32))
    assert ok.clamped == 0 and not ok.frame.flags & Flag.CLAMPED


def test_errors(rig: Rig) -> None:
    pose = Pose(rotation=np.eye(3), translation=np.array([0.0, 0.0, -600.0]))
    with pytest.raises(ValueError, match="q: expected shape"):
        pack(0, Flag(0), pose, np.zeros((9, 2), np.float32), q=np.zeros(3))
    with pytest.raises(ValueError, match="residuals: expected finite"):
        pack(0, Flag(0), pose, np.zeros((9, 3), np.float32))
    with pytest.raises(ValueError, match="residuals: expected finite"):
        pack(0, Flag(0), pose, np.full((9, 2), np.nan, np.float32))
    packet = bytearray(pack(0, Flag(0), pose, np.zeros((9, 2), np.float32)).packet)
    packet[5] ^= 0xFF
    with pytest.raises(PacketError):
        unpack_geometry(rig, bytes(packet))
