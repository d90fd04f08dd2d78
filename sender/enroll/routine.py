"""The guided enrollment routine: the prompts ``facewire model build --guided`` gives, in order,
how long each records, and which region's states each feeds.

A prompt runs as a *lead-in* of ``Schedule.lead_s`` seconds ("get ready": the person reads
the prompt and makes the face; nothing is recorded) and then a *take* of
``Schedule.record_s`` seconds, recorded. Times are frame times (``VideoFrame.time`` from the
first frame of the source), so a camera runs the routine in real time and a video file
standing in for it runs the same schedule on its own clock, however fast it is read.

The prompts (``ROUTINE``) and the regions (``models.regions.REGIONS``) they feed:

===========  ==============================  ============================================
prompt       the person is asked to          feeds
===========  ==============================  ============================================
neutral      look at the camera, relaxed     the neutral frame (the rest state of every
                                             region, and the base texture's first view)
brows_up     raise the eyebrows              forehead
frown        draw the brows together         brow_furrow
eyes_closed  close both eyes                 eyelid_left, eyelid_right
look_left    look left, head still           eyeball_left, eyeball_right
look_right   look right, head still          eyeball_left, eyeball_right
look_up      look up, head still             eyeball_left, eyeball_right
look_down    look down, head still           eyeball_left, eyeball_right
smile        smile, lips closed              mouth
smile_wide   smile wide, showing the teeth   mouth
mouth_open   open the mouth wide             mouth
===========  ==============================  ============================================

``Guide`` carries the takes' frames into the build (``sender.enroll.build.build_model``): the
neutral frame is chosen among the neutral take's frames (``sender.enroll.fit``), and each
region's states other than its rest state among the frames of the takes that feed it
(``sender.enroll.layers``), the cue levels spanning those frames and the neutral take's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the command's parser reads this module: no numpy at import
    from facewire.models.manifest import SourceRange

EYES = ("eyeball_left", "eyeball_right")
LEAD_S = 1.5  # default lead-in, seconds
RECORD_S = 2.5  # default take, seconds


@dataclass(frozen=True)
class Prompt:
    """One step of the routine.

    Attributes:
        name: its key, e.g. ``eyes_closed``.
        text: what the person is asked, as shown in the terminal and on the live page.
        feeds: the regions (``models.regions.REGION_NAMES``; every region is fed by some
            prompt) whose states it feeds; () for the neutral prompt, which feeds the
            neutral frame.
    """

    name: str
    text: str
    feeds: tuple[str, ...]


ROUTINE: tuple[Prompt, ...] = (
    Prompt("neutral", "Look at the camera with a relaxed, neutral face", ()),
    Prompt("brows_up", "Raise your eyebrows", ("forehead",)),
    Prompt("frown", "Frown: draw your brows together", ("brow_furrow",)),
    Prompt("eyes_closed", "Close your eyes", ("eyelid_left", "eyelid_right")),
    Prompt("look_left", "Look to your left, keep your head still", EYES),
    Prompt("look_right", "Look to your right, keep your head still", EYES),
    Prompt("look_up", "Look up, keep your head still", EYES),
    Prompt("look_down", "Look down, keep your head still", EYES),
    Prompt("smile", "Smile, lips closed", ("mouth",)),
    Prompt("smile_wide", "Smile wide, show your teeth", ("mouth",)),
    Prompt("mouth_open", "Open your mouth wide", ("mouth",)),
)
NEUTRAL = ROUTINE[0].name


@dataclass(frozen=True)
class Schedule:
    """How long each prompt's lead-in and take last, seconds (module docstring).

    Raises:
        ValueError: a lead-in below 0 or a take not above 0, or either not finite or over
            60 s (naming the option).
    """

    lead_s: float = LEAD_S
    record_s: float = RECORD_S

    def __post_init__(self) -> None:
        for option, value, low in (("--lead-seconds", self.lead_s, 0.0),
                                   ("--prompt-seconds", self.record_s, None)):
            ok = math.isfinite(value) and value <= 60 and (
                value >= 0 if low is not None else value > 0)
            if not ok:
                raise ValueError(f"{option}: expected {'0' if low is not None else 'more than 0'}"
                                 f" to 60 seconds, got {value}")

    def end(self, leads: int, takes: int) -> float:
        """When ``leads`` lead-ins and ``takes`` takes are over, seconds from the start."""
        return leads * self.lead_s + takes * self.record_s

    @property
    def seconds(self) -> float:
        """The whole routine's length, seconds, when no prompt is repeated."""
        return len(ROUTINE) * (self.lead_s + self.record_s)


@dataclass(frozen=True)
class Guide:
    """Which frames of the recording the build chooses from (module docstring).

    Attributes:
        neutral: frame indices of the neutral take.
        regions: per region name, the frame indices of the takes that feed it.
        origin: what was recorded (``camera:0``, a video file's name): the model's
            ``info.source_video``.
        origin_range: the frames of that video file the recording spans (the model's
            ``info.source``, which ``bench quality`` checks), or None for a camera (the
            recording itself is not kept).
    """

    neutral: frozenset[int]
    regions: Mapping[str, frozenset[int]]
    origin: str = ""
    origin_range: SourceRange | None = None

    @classmethod
    def of_labels(cls, labels: Sequence[str | None], origin: str = "",
                  origin_range: SourceRange | None = None) -> Guide:
        """The guide of a recording whose frame ``i`` was taken for prompt ``labels[i]``
        (a ``Prompt.name``; None: a frame of a take that was repeated)."""
        feeds = {p.name: p.feeds for p in ROUTINE}
        regions: dict[str, set[int]] = {r: set() for p in ROUTINE for r in p.feeds}
        for i, label in enumerate(labels):
            for region in feeds.get(label or "", ()):
                regions[region].add(i)
        return cls(frozenset(i for i, label in enumerate(labels) if label == NEUTRAL),
                   {name: frozenset(frames) for name, frames in regions.items()}, origin,
                   origin_range)
