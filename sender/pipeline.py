"""The sender pipeline: one camera frame in, one packet out.

Per frame (``SenderPipeline.process``), each stage timed (``SenderOutput.timings``, s):

1. ``track``: the frame converted to grey once (the sampler reads the same grey frame),
   ``sender.tracker.LandmarkTracker`` -> 68 image points, or None (no face). Whom it
   follows: the model's person when the model stores their face descriptors
   (``PersonModel.descriptors``, ``sender.identity.Person``): that person only, whoever
   else is in the picture, larger or not; while they are out of it, no face (the packets
   say the face is absent) until they are back (``sender.tracker``, "Identity"; a live
   sender, ``identify_apart``, has the checks' descriptors computed in a process of its
   own and takes the answers frames later). A model without descriptors (built before
   they were stored): the largest face, as the tracker does without a person;
   ``identity_warning`` is the line the commands print about it.
2. ``pose``: ``sender.lift.pose_and_lift`` (the weighted robust fit of
   ``sender.pose.PoseSolver`` to the model's landmarks under the current expression,
   alternated with the lift; started from the previous frame's raw pose and expression) and
   ``sender.smoothing.PoseFilter`` (One-Euro).
3. ``lift``: ``sender.lift.Lifter`` -> (9, 3) model-space residuals of the non-rigid
   points, lifted again with the filtered pose (the one that is sent, so the receiver's
   points land on the tracked ones), with per-point validity.
4. ``heuristics``: ``sender.heuristics.ResidualFilter`` (decay, mirror completion, jump hold,
   face loss); the residuals it returns are then projected once on the rig's tangent planes
   (``Rig.to_tangent``, what the packet carries) and taken back to model space
   (``Rig.from_tangent``): ``SenderOutput.residuals`` is exactly the geometry the packet
   can carry, before quantisation.
5. ``sample``: ``sender.appearance.AppearanceSampler`` reads every region's five offset
   16 x 16 samples from the grey frame at the sent pose and residuals.
6. ``classify``: ``sender.classify.RegionClassifiers`` -> one Q per region, in the model's
   region order (the packet's Q slots); an open eye's eyelid Q is then held at most at its
   rest state (``sender.eyegate``).
7. ``learn`` (on by default; ``learn=False``, ``--no-learn``, turns it off):
   ``sender.learn.Learner`` watches how far each region's best template lies from the
   frame's sample; an appearance held unlike every template for a few clean frames becomes
   a model update (a new state of that region), applied at once to the pipeline's model,
   classifier and eye gate, kept in ``updates`` for the transport and the log; ``serial``
   is the model version the packets' Q refer to.
8. ``shade``: ``sender.shading.ShadingEstimator`` -> the light's log-gain field relative to
   the model's texture, fitted on plain skin of the grey frame at the sent pose and
   residuals, smoothed over time.
9. ``pack``: ``sender.pack.pack`` -> the ``Frame`` and its 43 bytes, its ``serial`` the
   pipeline's.

No face, or no acceptable pose for the face the tracker saw: the residual filter runs its
face-loss branch (decay, ``TRACKING_LOST``), the pose filter restarts, and the packet carries
the last sent pose (the protocol's default frontal pose at 600 mm before any), the last
Q values (0 before any) and the last light (zeros before any). When the tracker saw a face
but the pose was rejected, ``FACE_PRESENT`` is still set (the flag follows the tracker)
together with ``TRACKING_LOST``. A face the tracker acquired on a frame that followed another
one (a switch to a larger face, or the tracked face lost and another found in the same frame:
``TrackResult.acquired``) is a new face: the pose is fitted from scratch, the pose filter
restarts, the light's smoothing starts again from that face's first fit, and the packet is
``REACQUIRED`` (``ResidualFilter.restart``), as after a loss.

Hello: the model's sha256 and size, the rate, the camera (the ``models.geometry.Intrinsics``
converted to the wire's ``protocol.control.Camera`` here, the sender's one place), the
quantiser table, and the
model's region names (``PersonModel.regions``, in packet order, the first 8). A model without
regions (built without appearance) gives an empty list, and every Q slot carries 0
(neutral); Q slots beyond the named regions carry 0 and mean nothing. Naming regions the
model does not have would promise the receiver layers it cannot find.

``encode_video`` runs the pipeline over a video into a packet log (``protocol.log``), each
record stamped with the frame's presentation time in seconds from the start of the file.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.models.geometry import Intrinsics, Pose
from facewire.models.infra.progress import Progress, no_progress
from facewire.models.infra.sound import SoundError, read_sound
from facewire.models.landmarks import N_LANDMARKS
from facewire.models.modelfile import PersonModel, load_model, model_summary
from facewire.models.patch import TexturePatch
from facewire.models.rig import Rig
from facewire.models.update import Update
from facewire.protocol.control import Camera, Hello
from facewire.protocol.log import LogWriter
from facewire.protocol.opus import DEFAULT_BITRATE, FRAME_S, Encoder
from facewire.protocol.packet import N_REGIONS, Flag, Frame
from facewire.protocol.rate import MAX_RATE_HZ, MIN_RATE_HZ, NOMINAL_HZ, payload_kbps, stream_rate
from facewire.protocol.voice import SEQ_MODULO as VOICE_SEQ_MODULO
from facewire.protocol.voice import VoicePacket
from facewire.protocol.voice import encode as encode_voice
from facewire.sender.appearance import AppearanceSampler
from facewire.sender.capture import (
    CaptureError,
    estimate_intrinsics,
    open_source,
    read_calibration,
    scale_intrinsics,
)
from facewire.sender.classify import RegionClassifiers
from facewire.sender.eyegate import EyeGate
from facewire.sender.heuristics import ResidualFilter
from facewire.sender.identity import Person
from facewire.sender.learn import Learner, can_learn
from facewire.sender.lift import Lifter, LiftResult, pose_and_lift
from facewire.sender.pack import Packed, pack
from facewire.sender.pose import PoseSolver
from facewire.sender.shading import ShadingEstimator
from facewire.sender.smoothing import PoseFilter
from facewire.sender.tracker import LandmarkTracker
from facewire.sender.voice import FileVoice


@dataclass(frozen=True)
class SenderOutput:
    """One processed frame.

    Attributes:
        frame: what was packed (its flags include CLAMPED when set); pre-quantisation values
            are in ``rotation``/``translation``/``residuals``.
        packet: the encoded 43-byte packet.
        points: (68, 2) float tracker points, pixels, or None (no face).
        rotation: (3, 3) float64 pre-quantisation pose (model -> GL camera), or None when
            this frame has no pose (the packet then repeats the last one, and its Q).
        translation: (3,) float64 mm, or None.
        residuals: (9, 3) float32 pre-quantisation model-space displacements after the
            heuristics, projected on the tangent planes (what the packet can carry).
        q: (R,) float32 pre-quantisation Q of the model's R regions (packet order).
        offsets: (R,) int64 the winning sample offset of each region (``models.regions``
            ``OFFSETS``), or None when this frame was not classified.
        samples: (R, 5, 16, 16) float32 the regions' samples that were classified, or None
            with ``offsets``.
        timings: seconds per stage: ``track``, ``pose``, ``lift``, ``heuristics``, ``sample``,
            ``classify``, ``learn``, ``shade``, ``pack``.
        detected: the tracker ran its full-frame detector on this frame.
        identified: the tracker asked for an identity check on this frame
            (``sender.identity``; its descriptor computed here, or apart).
        clamped: values clamped by the quantisers on this frame.
        grazing: non-rigid points whose lift was capped at a grazing angle.
        update: the model update learned on this frame (``sender.learn``), or None; the
            frame's own Q came from the model before it.
        update_bytes: that update's bytes, encoded against the model version before it
            (``models.update.encode_update``), or None.
    """

    frame: Frame
    packet: bytes
    points: np.ndarray | None
    rotation: np.ndarray | None
    translation: np.ndarray | None
    residuals: np.ndarray
    q: np.ndarray
    offsets: np.ndarray | None = None
    samples: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)
    detected: bool = False
    identified: bool = False
    clamped: int = 0
    grazing: int = 0
    update: Update | None = None
    update_bytes: bytes | None = None


class SenderPipeline:
    """Track, pose, lift, filter and pack frames of one stream (module docstring).

    Args:
        model: the person model.
        camera: the sender camera's intrinsics (``sender.capture.estimate_intrinsics`` or a
            calibration).
        rate_hz: the stream's nominal rate (announced in the Hello; the time step of a frame
            whose time does not advance).
        learn: learn unseen appearance during the session (``sender.learn``; only a model
            loaded from its file, with the regions of ``models.regions.REGIONS``, can).
        background: capture learned states on a worker thread (a live stream: the frames
            go on meanwhile), not on the frame that makes them due.
        heal: while learning, heal the base texture too (``sender.heal``: texture patches).
        identify_apart: compute the identity checks' descriptors in a process of their own
            (a live stream: the frames go on meanwhile, and the tracker takes the answers
            frames later; ``sender.identity``), not on the frame that asks; ``close`` ends
            that process.

    Attributes:
        model: the model as learned so far (version ``serial``).
        learner: the ``sender.learn.Learner``, or None when not learning.
    """

    def __init__(self, model: PersonModel, camera: Intrinsics, rate_hz: float = NOMINAL_HZ,
                 learn: bool = True, background: bool = False, heal: bool = True,
                 identify_apart: bool = False) -> None:
        if not isinstance(model, PersonModel):
            raise ValueError(f"model: expected a PersonModel, got {type(model).__name__}")
        if not isinstance(camera, Intrinsics):
            raise ValueError(f"camera: expected a models.geometry.Intrinsics, got "
                             f"{type(camera).__name__}")
        if not (np.isfinite(rate_hz) and MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ):
            raise ValueError(f"rate_hz: expected a number in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}], "
                             f"got {rate_hz!r}")
        self.model = model
        self.camera = camera
        self.rate_hz = float(rate_hz)
        self.rig = Rig(model.mesh)
        landmarks = model.mesh.vertices[model.mesh.landmarks].astype(np.float64)
        self.solver = PoseSolver(landmarks, camera)
        self.lifter = Lifter(self.rig, camera)
        self.person = None if model.descriptors is None \
            else Person(model.descriptors, apart=identify_apart)
        self.tracker = LandmarkTracker(person=self.person)
        self.pose_filter = PoseFilter()
        self.residual_filter = ResidualFilter()
        regions = model.regions[:N_REGIONS]
        self.sampler = AppearanceSampler(model.mesh, self.rig, camera,
                                         tuple(r.name for r in regions))
        self.classifiers = RegionClassifiers([r.templates for r in regions]) if regions \
            else None
        self._landmarks = landmarks
        self.eye_gate = EyeGate(regions, landmarks)
        self.learner = Learner(model, camera, self.rig, self.classifiers, background, heal) \
            if learn and self.classifiers is not None and can_learn(model) else None
        self.shading = ShadingEstimator(model, self.rig, camera)
        self.reset()

    def close(self) -> None:
        """End the identity process, if the pipeline has one."""
        if self.person is not None:
            self.person.close()

    @property
    def updates(self) -> list[Update]:
        """The model updates this session issued, in order (the transport sends them, the log
        keeps them); empty when not learning."""
        return [] if self.learner is None else self.learner.updates

    @property
    def serial(self) -> int:
        """The model version the packets' Q values refer to: the last update's serial, 0 for
        the model file."""
        return 0 if self.learner is None else self.learner.serial

    def hello(self) -> Hello:
        """The Hello announcing this stream (module docstring)."""
        summary = model_summary(self.model)
        regions = tuple(r.name for r in self.model.regions)[:N_REGIONS]
        return Hello(model_sha256=summary["sha256"], model_bytes=summary["bytes"],
                     rate_hz=self.rate_hz, camera=wire_camera(self.camera), regions=regions)

    def reset(self) -> None:
        """Forget the stream: tracker, filters, last pose and the sequence number."""
        self.tracker.reset()
        self.pose_filter.reset()
        self.residual_filter.reset()
        self.shading.reset()
        self._raw: Pose | None = None
        self._expression: np.ndarray | None = None  # the last raw lift's residuals
        default = Frame()
        self._sent = Pose(rotation=np.eye(3), translation=default.translation.astype(np.float64))
        self._seq = 0
        self._time: float | None = None
        self._q = np.zeros(len(self.sampler.names), np.float32)
        self._q_serial = self.serial  # the model version self._q refers to

    def set_slot(self, slot: int) -> None:
        """Number the next packet ``slot`` (mod 65536): the slots of a stream that had no
        frame (``sender.slots``) leave their numbers unused."""
        self._seq = slot % (1 << 16)

    def process(self, image: np.ndarray, time_s: float) -> SenderOutput:
        """Process one frame: the module docstring's nine stages, each timed.

        Args:
            image: (H, W, 3) uint8 BGR frame.
            time_s: its time, seconds (non-decreasing within a stream).

        Returns:
            The packet and what went into it.
        """
        dt = self._time_step(time_s)
        clock = time.perf_counter
        t0 = clock()
        gray = _gray(image)
        tracked = self.tracker.track(gray, image if gray is not image else None)
        points = tracked.points
        t1 = clock()
        pose = self._pose(tracked.acquired, points, dt)
        t2 = clock()
        lifted = None
        if pose is not None:
            assert points is not None  # a pose comes from tracked points
            lifted = self.lifter.lift(points, pose)
        t3 = clock()
        tangent, residuals, flags = self._heuristics(lifted, points is not None, dt)
        t4 = clock()
        offsets = samples = None
        t5 = t4
        if pose is not None:
            self._sent = pose
            if self.classifiers is not None:
                samples = self.sampler.sample(gray, pose.rotation, pose.translation,
                                              residuals)
                t5 = clock()
                result = self.classifiers.classify(samples)
                assert points is not None
                self._q, offsets = self.eye_gate.apply(result.q, points), result.offset
                self._q_serial = self.serial
        t6 = clock()
        update = None
        if self.learner is not None and samples is not None:
            assert pose is not None and points is not None
            update = self.learner.observe(image, points, pose.rotation, pose.translation,
                                          residuals, samples, result, flags, time_s)
            if update is not None:
                self._learned(update)
        t7 = clock()
        if pose is not None:
            self.shading.estimate(gray, pose.rotation, pose.translation, residuals, dt)
        t8 = clock()
        packed = self._pack(flags, tangent)
        t9 = clock()
        return SenderOutput(
            frame=packed.frame, packet=packed.packet,
            points=None if points is None else np.asarray(points, np.float64).reshape(
                N_LANDMARKS, 2),
            rotation=None if pose is None else pose.rotation.copy(),
            translation=None if pose is None else pose.translation.copy(),
            residuals=residuals, q=self._q.copy(), offsets=offsets, samples=samples,
            timings={"track": t1 - t0, "pose": t2 - t1, "lift": t3 - t2,
                     "heuristics": t4 - t3, "sample": t5 - t4, "classify": t6 - t5,
                     "learn": t7 - t6, "shade": t8 - t7, "pack": t9 - t8},
            detected=bool(tracked.detected), identified=tracked.identified,
            clamped=packed.clamped,
            grazing=0 if lifted is None else int(lifted.grazing.sum()), update=update,
            update_bytes=None if update is None or self.learner is None
            else self.learner.update_bytes[update.serial])

    def _learned(self, update: Update) -> None:
        """Take the learner's new model: its region's templates into the classifier, its
        rest state into the eye gate, from the next frame on."""
        assert self.learner is not None and self.classifiers is not None
        self.model = self.learner.model
        if isinstance(update, TexturePatch):  # the texture only: nothing to classify anew
            return
        regions = self.model.regions[:N_REGIONS]
        changed = [r.name for r in regions].index(update.region)
        self.classifiers = RegionClassifiers([
            regions[r].templates if r == changed else c
            for r, c in enumerate(self.classifiers.regions)])
        self.eye_gate = EyeGate(regions, self._landmarks)

    def _time_step(self, time_s: float) -> float:
        """This frame's time step, s: since the last frame, or 1 / rate when time stood still."""
        if not np.isfinite(time_s):
            raise ValueError(f"time_s: expected a finite time in seconds, got {time_s!r}")
        dt = 1.0 / self.rate_hz
        if self._time is not None and time_s > self._time:
            dt = float(time_s - self._time)
        self._time = float(time_s)
        return dt

    def _pose(self, acquired: bool, points: np.ndarray | None, dt: float) -> Pose | None:
        """Stage 2: the filtered pose of the tracked points, or None (no face, or no fit).

        A newly acquired face starts from scratch; so does a fit that failed from the last
        frame's raw pose and expression. Without a pose the pose filter restarts.
        """
        pose = None
        if acquired and self._raw is not None:  # another face than the last frame's
            self._raw = self._expression = None
            self.pose_filter.reset()
            self.residual_filter.restart()
            self.shading.restart()
        if points is not None:
            raw, lifted = pose_and_lift(self.solver, self.lifter, self.rig, points, self._raw,
                                        self._expression)
            if raw is None and self._raw is not None:  # re-acquire from scratch
                raw, lifted = pose_and_lift(self.solver, self.lifter, self.rig, points, None,
                                            None)
            self._raw = raw
            if raw is not None:
                assert lifted is not None  # pose_and_lift returns both or neither
                self._expression = lifted.residuals
                pose = self.pose_filter.step(raw, dt)
        if pose is None:
            self._raw = None
            self._expression = None
            self.pose_filter.reset()
        return pose

    def _heuristics(self, lifted: LiftResult | None, face: bool,
                    dt: float) -> tuple[np.ndarray, np.ndarray, Flag]:
        """Stage 4: the residual filter, then the tangent projection the packet carries.

        Returns:
            The (9, 2) tangent coordinates, the (9, 3) model-space residuals they stand for,
            and the packet's flags (``FACE_PRESENT`` when the tracker saw a face).
        """
        if lifted is None:
            out = self.residual_filter.step(None, None, dt)
        else:
            out = self.residual_filter.step(lifted.residuals, lifted.valid, dt)
        tangent = self.rig.to_tangent(out.residuals)
        residuals = self.rig.from_tangent(tangent)
        flags = out.flags | (Flag.FACE_PRESENT if face else Flag(0))
        return tangent, residuals, flags

    def _pack(self, flags: Flag, tangent: np.ndarray) -> Packed:
        """Stage 9: the packet of the last sent pose, Q (with the model version that Q refers
        to: a frame that issued an update was classified before it) and light, and the next
        sequence number."""
        q = np.zeros(N_REGIONS, np.float32)
        q[:len(self._q)] = self._q
        packed = pack(self._seq, flags, self._sent, tangent, q, self._q_serial,
                      self.shading.sent)
        self._seq = (self._seq + 1) % (1 << 16)
        return packed


def identity_warning(model: PersonModel, name: str | os.PathLike[str]) -> str | None:
    """The one line to show when the sender cannot hold the model's person (a model without
    descriptors, module docstring, 1), else None; ``name`` names the model file."""
    if model.descriptors is not None:
        return None
    return (f"warning: {os.fspath(name)} stores no face descriptors (built before they were): "
            f"the sender cannot hold its person and follows the largest face; rebuild it "
            f"with 'facewire model build' to follow only that person")


def wire_camera(camera: Intrinsics) -> Camera:
    """The intrinsics as the Hello carries them (``protocol.control.Camera``)."""
    return Camera(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)


def _gray(image: np.ndarray) -> np.ndarray:
    """A BGR uint8 frame in grey; anything else is left to the tracker to accept or refuse."""
    if isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3 \
            and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return image


def sender_camera(width: int, height: int, focal: float | None = None,
                  calib: str | os.PathLike[str] | None = None) -> Intrinsics:
    """The camera of a ``width`` x ``height`` source: a calibration file (scaled to the
    source's size), else ``--focal``, else the guess (``sender.capture``)."""
    if calib is not None:
        if focal is not None:
            raise ValueError("--focal and --calib: give one or the other, not both")
        return scale_intrinsics(read_calibration(calib), width, height, name=str(calib))
    return estimate_intrinsics(width, height, focal)


def encode_video(model_path: str | os.PathLike[str], source: str | os.PathLike[str],
                 out_log: str | os.PathLike[str], frames: slice | None = None,
                 focal: float | None = None, calib: str | os.PathLike[str] | None = None,
                 progress: Progress = no_progress, learn: bool = True,
                 warn: Callable[[str], None] | None = None, heal: bool = True,
                 audio: bool = True, voice_bitrate: int = DEFAULT_BITRATE) -> dict[str, Any]:
    """Run the sender pipeline over a video (or folder of images) into a packet log, with
    each model update it learns after the packet of the frame that learned it, and the
    video's sound as voice records (``sender.voice.FileVoice``: frame ``j`` holds the sound
    from the first frame's time plus ``j`` 20-ms frames, logged at its end's time, as a live
    sender sends it once captured), interleaved with the packets by time.

    Args:
        model_path: the person model (``.fwm``).
        source: a video file or a folder of images (``sender.capture.open_source``).
        out_log: the ``.fwlog`` to write (replaced if it exists).
        frames: which frames (``models.infra.video.frame_range``); all by default.
        focal: focal length in pixels (``--focal``), else estimated.
        calib: a calibration JSON file (``--calib``).
        progress: wraps an iterable to show progress: ``progress(items, label, total)``.
        learn: learn unseen appearance (``sender.learn``); ``--no-learn`` turns it off.
        warn: called once, before encoding, with ``identity_warning``'s line when the model
            cannot hold its person, and after encoding with a line when the video's sound
            track is missing or cannot be decoded.
        heal: while learning, heal the base texture too (``sender.heal``).
        audio: keep the video's sound in the log (``--no-audio``: not).
        voice_bitrate: Opus's rate, bit/s.

    Returns:
        ``frames``, ``face_frames`` (the tracker saw a face), ``packets``, ``payload_kbps``
        (at 30 Hz), ``clamped`` (frames with CLAMPED), ``clamped_values``, ``held``,
        ``mirrored``, ``tracking_lost`` (frames with that flag), ``grazing`` (capped lifts),
        ``updates`` (model updates learned), ``update_regions`` (their regions, in order),
        ``voice_packets`` (voice records), ``seconds`` (wall time), ``rate_hz``, ``camera``,
        ``model_sha256``, ``log``.

    Raises:
        ModelFileError: the model is missing or corrupt (names the file).
        CaptureError: the source is missing or unreadable, or holds no frame (names it); a
            frame that cannot be decoded ends the encoding, and the message says how many
            packets the log keeps from before it.
    """
    start = time.perf_counter()
    model = load_model(model_path)
    src = open_source(str(source), frames=slice(0, None) if frames is None else frames,
                      pace=False)
    camera = sender_camera(src.width, src.height, focal, calib)
    pipeline = SenderPipeline(model, camera, rate_hz=stream_rate(src.rate_hz), learn=learn,
                              heal=heal)
    identity = identity_warning(model, model_path)
    if identity is not None and warn is not None:  # once the source is open
        warn(identity)
    hello = pipeline.hello()
    sound, unheard = None, None  # unheard: why the log has no sound, said once it is done
    if audio and not Path(source).is_dir():
        try:
            sound = read_sound(source)
        except SoundError as error:  # the frames may still decode: the face goes on
            unheard = f"{error}; the log holds the face alone"
        else:
            if sound is None:
                unheard = f"{source} has no sound track: the log holds the face alone"
    if sound is not None:
        hello = dataclasses.replace(hello, voice_bitrate=voice_bitrate)
    talk = None if sound is None else _Talk(FileVoice(sound), Encoder(voice_bitrate))
    counts = {"frames": 0, "face_frames": 0, "packets": 0, "clamped": 0, "clamped_values": 0,
              "held": 0, "mirrored": 0, "tracking_lost": 0, "grazing": 0, "updates": 0,
              "voice_packets": 0}
    try:
        with src, LogWriter(out_log, hello) as log:
            _encode_frames(src, pipeline, log, counts, progress, talk)
    except CaptureError as exc:  # a frame that cannot be decoded: keep what came before it
        if counts["frames"] == 0:
            Path(out_log).unlink(missing_ok=True)
            raise
        raise CaptureError(f"{exc}; the {counts['frames']} packets encoded before it are in "
                           f"{out_log}") from None
    if counts["frames"] == 0:
        Path(out_log).unlink(missing_ok=True)
        raise CaptureError(f"{source}: no frames to encode")
    if unheard is not None and warn is not None:
        warn(unheard)
    return {
        **counts,
        "update_regions": [u.region for u in pipeline.updates],
        "payload_kbps": round(payload_kbps(NOMINAL_HZ), 3),
        "seconds": round(time.perf_counter() - start, 3),
        "rate_hz": pipeline.rate_hz,
        "camera": {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
                   "width": camera.width, "height": camera.height},
        "model_sha256": hello.model_sha256,
        "log": str(out_log),
    }


@dataclass
class _Talk:
    """``encode_video``'s voice: the file's sound, its encoder and the next frame's number."""

    voice: FileVoice
    encoder: Encoder
    next: int = 0

    def until(self, log: LogWriter, end: float) -> int:
        """Log every voice frame that ends by ``end`` (s) and is not logged yet; how many."""
        count = 0
        while self.voice.t0 + (self.next + 1) * FRAME_S <= end + 1e-9:
            opus = self.encoder.encode(self.voice.frame(self.next))
            log.write_voice(encode_voice(VoicePacket(self.next % VOICE_SEQ_MODULO, opus)),
                            self.voice.t0 + (self.next + 1) * FRAME_S)
            self.next += 1
            count += 1
        return count


def _encode_frames(src: Any, pipeline: SenderPipeline, log: LogWriter, counts: dict[str, int],
                   progress: Progress, talk: _Talk | None = None) -> None:
    """Run the pipeline on every frame of ``src`` into ``log``, adding to ``counts``; with
    ``talk``, the voice frames that end by each frame's time after its packet, and at the end
    those of the last frame's period."""
    end = None
    for frame in progress(iter(src), "encoding", src.frames or None):
        if talk is not None and end is None:
            talk.voice.t0 = frame.time
        end = frame.time
        out = pipeline.process(frame.image, frame.time)
        log.write(out.packet, frame.time)
        if out.update is not None and out.update_bytes is not None:  # after the frame's packet
            log.write_update(frame.time, out.update.serial, out.update_bytes)
        if talk is not None:
            counts["voice_packets"] += talk.until(log, frame.time)
        flags = out.frame.flags
        counts["frames"] += 1
        counts["packets"] += 1
        counts["face_frames"] += out.points is not None
        counts["clamped"] += bool(flags & Flag.CLAMPED)
        counts["clamped_values"] += out.clamped
        counts["held"] += bool(flags & Flag.HELD)
        counts["mirrored"] += bool(flags & Flag.MIRRORED)
        counts["tracking_lost"] += bool(flags & Flag.TRACKING_LOST)
        counts["grazing"] += out.grazing
        counts["updates"] += out.update is not None
    if talk is not None and end is not None:
        counts["voice_packets"] += talk.until(log, end + 1.0 / pipeline.rate_hz)
