"""Quantise one frame's pose, residuals, Q values and flags into the protocol's packet.

What goes in (``protocol.packet.QUANTISERS`` fixes the ranges and steps):

- rotation: the pose's rotation as a rotation vector (``models.geometry.rotation_vector``;
  radians in the ``Frame``, degrees on the wire);
- translation: mm;
- residuals: the (9, 2) tangent-frame residuals (u, v), mm (``Rig.to_tangent`` of the
  model-space displacements, which the pipeline computes once);
- q: the 8 region values (neutral 0 until the appearance work lands);
- shade: the light's log-gain field (``sender.shading``; zeros: the model's own light);
- flags and the 16-bit sequence number.

Clamping: a value outside its quantiser's range is clamped and the packet carries
``Flag.CLAMPED`` (``protocol.packet.encode_frames``); ``pack`` returns the number of
clamped values with the packet so the pipeline counts and reports them.

Decoding back to geometry (``unpack_geometry``) is what a receiver does: rotation matrix,
translation and ``Rig.from_tangent`` of the residuals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facewire.models.geometry import Pose, rotation_matrix, rotation_vector
from facewire.models.rig import Rig
from facewire.protocol.packet import (
    N_REGIONS,
    N_RESIDUAL_POINTS,
    N_SHADE,
    SEQ_MODULO,
    Flag,
    Frame,
    decode,
    encode_frames,
)


@dataclass(frozen=True)
class Packed:
    """One packed frame: the ``Frame`` (pre-encode values), its bytes, and clamped values."""

    frame: Frame
    packet: bytes
    clamped: int


def pack(seq: int, flags: Flag, pose: Pose, residuals: np.ndarray,
         q: np.ndarray | None = None, serial: int = 0,
         shade: np.ndarray | None = None) -> Packed:
    """Quantise and encode one frame.

    Args:
        seq: sequence number (taken modulo 65536).
        flags: the frame's flags (``Flag.CLAMPED`` is added by the encoder when needed).
        pose: the pose to send.
        residuals: (9, 2) finite tangent-frame residuals (u, v), mm, ``NONRIGID`` order
            (``Rig.to_tangent``).
        q: (8,) region values, layers; None for neutral (all 0).
        serial: the model version ``q`` refers to (0: the model file; ``sender.learn``).
        shade: (3,) the light's log-gain field (s0, s1, s2); None for the model's own light.

    Returns:
        The frame (its ``flags`` include CLAMPED when set), the 43-byte packet and the
        number of clamped values.
    """
    q = np.zeros(N_REGIONS, np.float32) if q is None else np.asarray(q, np.float32)
    if q.shape != (N_REGIONS,):
        raise ValueError(f"q: expected shape ({N_REGIONS},), got {q.shape}")
    uv = np.asarray(residuals, np.float32)
    if uv.shape != (N_RESIDUAL_POINTS, 2) or not np.isfinite(uv).all():
        raise ValueError(f"residuals: expected finite ({N_RESIDUAL_POINTS}, 2) tangent "
                         f"residuals, got shape {uv.shape}")
    frame = Frame(seq=int(seq) % SEQ_MODULO, flags=Flag(int(flags)),
                  rotation=rotation_vector(pose.rotation).astype(np.float32),
                  translation=np.asarray(pose.translation, np.float32).copy(),
                  residuals=uv.copy(), q=q, serial=int(serial),
                  shade=np.zeros(N_SHADE, np.float32) if shade is None
                  else np.asarray(shade, np.float32).reshape(N_SHADE).copy())
    packets, clamped = encode_frames(frame.to_record().reshape(1))
    if clamped[0]:
        frame.flags |= Flag.CLAMPED
    return Packed(frame, packets[0].tobytes(), int(clamped[0]))


def unpack_geometry(rig: Rig, packet: bytes) -> tuple[Frame, Pose, np.ndarray]:
    """Decode a packet into the frame, its pose and its (9, 3) model-space residuals.

    Raises:
        protocol.packet.PacketError: the packet is invalid.
    """
    frame = decode(packet)
    pose = Pose(rotation=rotation_matrix(frame.rotation),
                translation=frame.translation.astype(np.float64))
    return frame, pose, rig.from_tangent(frame.residuals)
