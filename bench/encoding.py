"""The sender's side of a measured run: a clip through the real sender pipeline, decoded.

``encode_frames`` runs ``sender.pipeline.SenderPipeline`` over the frames in order (or each
frame as a stream of its own, ``independent``) and keeps, besides each frame's packet, what
the measures need (``Run``): the tracker's 68 points, the frame itself, the mean grey level
of the landmarks' box, the regions' enrollment cues (``sender.cues.region_cues``)
and the eye aspect ratios, and a crop of the eyes for the plots. ``decode_run`` decodes the
packets with ``protocol.packet.decode_frames``, so a measurement sees only what a receiver
sees; every packet must be ``PACKET_BYTES`` long and decode. A sender that learns during the
session (``sender.learn``) classifies later frames against a newer model version; ``Run``'s
``versions`` holds, for each serial the packets name, the model the sender classified those
frames with (its ``model`` before the frame), which a receiver holding the session's updates
renders them with (``bench.rendering``). ``bench quality`` and the
build's self-check (``bench.selfcheck``) both measure through them.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple

import cv2
import numpy as np

from facewire.models.infra.progress import Progress
from facewire.models.infra.video import VideoFrame
from facewire.models.landmarks import eye_aspect_ratio
from facewire.models.modelfile import PersonModel
from facewire.models.regions import REGION_NAMES
from facewire.protocol.packet import PACKET_BYTES, decode_frames
from facewire.sender.cues import region_cues
from facewire.sender.pipeline import SenderPipeline


class Run(NamedTuple):
    """What the sender pipeline made of each frame of the range, in order (F frames)."""

    indices: list[int]  # video frame indices
    times: list[float]  # seconds
    packets: list[bytes]
    tracked: list[np.ndarray | None]  # (68, 2) tracker points, None without a face
    images: list[np.ndarray]  # the frames, for the rendering and x264 comparisons
    brightness: np.ndarray  # (F,) mean grey of the landmarks' box, NaN without a face
    cues: np.ndarray | None  # (F, regions) enrollment cues, NaN where not sampled; None
    #                          when the model's regions are not the ones the cues define
    ratios: np.ndarray  # (F, 2) eye aspect ratios, NaN where not sampled
    eyes: dict[int, np.ndarray]  # frame position -> BGR crop of the eyes (plots only)
    versions: dict[int, PersonModel]  # serial -> the model version it names (module docstring)


def encode_frames(pipeline: SenderPipeline, frames: Iterable[VideoFrame], progress: Progress,
                  total: int | None = None, keep_eyes: bool = False,
                  independent: bool = False) -> Run:
    """Run the sender pipeline over ``frames`` in order, keeping what the measures need.

    With ``independent``, the pipeline is reset before every frame, so each is encoded as
    the first frame of a stream (a fresh detection, no filter state): the self-check's
    frames, spread over a range, are not one stream (``bench.selfcheck``).
    """
    cued = pipeline.sampler.names == REGION_NAMES  # the cues are defined for these regions
    run = Run([], [], [], [], [], np.empty(0), None, np.empty(0), {}, {})
    brightness: list[float] = []
    cues: list[np.ndarray] = []
    ratios: list[np.ndarray] = []
    for frame in progress(frames, "encoding", total):
        if independent:
            pipeline.reset()
        model = pipeline.model  # the version this frame is classified with
        out = pipeline.process(frame.image, frame.time)
        run.versions.setdefault(out.frame.serial, model)
        if keep_eyes and out.points is not None:
            run.eyes[len(run.indices)] = _eye_crop(frame.image, out.points)
        brightness.append(np.nan if out.points is None
                          else _face_brightness(frame.image, out.points))
        if cued and out.samples is not None and out.points is not None:
            cues.append(region_cues(out.samples[:, 0], out.points, out.residuals))
            ratios.append(eye_aspect_ratio(out.points))
        else:
            cues.append(np.full(len(REGION_NAMES), np.nan))
            ratios.append(np.full(2, np.nan))
        run.indices.append(frame.index)
        run.times.append(frame.time)
        run.images.append(frame.image)
        run.packets.append(out.packet)
        run.tracked.append(out.points)
    return run._replace(brightness=np.array(brightness), cues=np.array(cues) if cued else None,
                        ratios=np.array(ratios))


def decode_run(packets: list[bytes], indices: list[int]) -> np.ndarray:
    """The sender's packets decoded: (F,) ``FRAME_DTYPE``; every one must be whole and valid.
    """
    sizes = {len(p) for p in packets}
    if sizes != {PACKET_BYTES}:
        raise ValueError(f"sender produced packets of {sorted(sizes)} bytes, "
                         f"expected {PACKET_BYTES}")
    decoded, errors = decode_frames(np.frombuffer(b"".join(packets), np.uint8)
                                    .reshape(len(packets), PACKET_BYTES))
    bad = [i for i, e in enumerate(errors) if e is not None]
    if bad:
        raise ValueError(f"sender packet of frame {indices[bad[0]]} does not decode: "
                         f"{errors[bad[0]]} ({len(bad)} such packets)")
    return decoded


def _face_brightness(image: np.ndarray, points: np.ndarray) -> float:
    """The mean grey level of the landmarks' bounding box."""
    h, w = image.shape[:2]
    x0, y0 = np.clip(np.floor(points.min(axis=0)).astype(int), 0, [w - 1, h - 1])
    x1, y1 = np.clip(np.ceil(points.max(axis=0)).astype(int) + 1, 1, [w, h])
    return float(cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_BGR2GRAY).mean())


def _eye_crop(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """A 2:1 crop of the frame around both eyes (iBUG 36-47), 240 x 120 px."""
    eyes = points[36:48]
    cx, cy = eyes.mean(axis=0)
    half = max(float(np.ptp(eyes[:, 0])) * 0.7, 8.0)
    x0, y0 = int(cx - half), int(cy - half / 2)
    x1, y1 = int(cx + half), int(cy + half / 2)
    h, w = image.shape[:2]
    crop = image[max(y0, 0):min(y1, h), max(x0, 0):min(x1, w)]
    if crop.size == 0:
        return np.zeros((120, 240, 3), np.uint8)
    return cv2.resize(crop, (240, 120), interpolation=cv2.INTER_AREA)
