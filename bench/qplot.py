"""A figure of the classifier's Q over time beside example frames (PNG, matplotlib Agg).

Each region's Q is drawn normalised, Q / (k - 1) in [0, 1] (k = its layer count), so regions
with different layer counts share one scale. One panel per family: the left and right
members of a pair (``eyelid_left`` / ``eyelid_right``, ``eyeball_left`` / ``eyeball_right``)
share a panel, every other region has its own; the y label says what 0 and 1 mean. NaN
values (no face) leave gaps. Above the panels, a strip of thumbnails (e.g. eye crops) in
time order, numbered; each number is marked at its time on every panel by a dashed line and
joined to its thumbnail.

Size (no tight bounding box, so it is exact): ``FIG_WIDTH_IN`` x (``HEADER_IN`` +
``STRIP_IN`` when there are thumbnails + ``PANEL_IN`` per panel) inches at ``DPI``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from facewire.bench.reference import q_series

FIG_WIDTH_IN = 10.0
HEADER_IN = 0.8  # title and x axis labels
STRIP_IN = 1.6
PANEL_IN = 1.3
DPI = 100
MAX_THUMBNAILS = 10  # more would be too small to read in the strip

# What 0 and 1 of the normalised Q mean, by family (the suffix _left/_right removed).
MEANING = {
    "forehead": "relaxed -> brows raised",
    "brow_furrow": "relaxed -> furrowed",
    "eyelid": "open -> closed",
    "eyeball": "gaze left -> right",
    "mouth": "closed -> open",
}


def plot_q(times: np.ndarray, q: dict[str, np.ndarray], layers: dict[str, int],
           thumbnails: Sequence[tuple[float, np.ndarray]], path: str | os.PathLike[str],
           title: str = "") -> None:
    """Write the figure (module docstring) as a PNG.

    Args:
        times: (N,) float seconds of the Q values.
        q: region name -> (N,) float Q in [0, k-1], NaN where there was no face.
        layers: region name -> k (>= 2) for every region in ``q``.
        thumbnails: at most ``MAX_THUMBNAILS`` (time_s, image) pairs, image (H, W, 3) BGR or
            (H, W) grey uint8; may be empty (no strip).
        path: the PNG to write.
        title: the figure's title.

    Raises:
        ValueError: ``q`` is empty, shapes or lengths disagree, times are not finite, a
            layer count is missing or < 2, there are more than ``MAX_THUMBNAILS`` thumbnails,
            or one is not a uint8 image with a finite time.
    """
    times = np.asarray(times, np.float64)
    if times.ndim != 1 or not np.isfinite(times).all():
        raise ValueError(f"times: expected a 1-D array of finite seconds, got {times.shape}")
    if not q:
        raise ValueError("q: no region to plot")
    curves = _normalised(q_series(q, times.shape), layers)
    if len(thumbnails) > MAX_THUMBNAILS:
        raise ValueError(f"thumbnails: {len(thumbnails)} given, at most {MAX_THUMBNAILS} fit "
                         f"the strip")
    thumbs = sorted((_thumbnail(i, t, image) for i, (t, image) in enumerate(thumbnails)),
                    key=lambda pair: pair[0])

    families: dict[str, list[str]] = {}
    for name in curves:
        families.setdefault(_family(name), []).append(name)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import ConnectionPatch

    n_panels = len(families)
    strip = STRIP_IN if thumbs else 0.0
    height = HEADER_IN + strip + PANEL_IN * n_panels
    fig = plt.figure(figsize=(FIG_WIDTH_IN, height), dpi=DPI)
    grid = fig.add_gridspec(n_panels + (1 if thumbs else 0), max(len(thumbs), 1),
                            height_ratios=([strip] if thumbs else []) + [PANEL_IN] * n_panels,
                            left=0.09, right=0.98, top=1 - 0.45 / height,
                            bottom=0.45 / height, hspace=0.25, wspace=0.05)
    top = 1 if thumbs else 0
    panels = [fig.add_subplot(grid[top, :])]
    panels += [fig.add_subplot(grid[top + p, :], sharex=panels[0]) for p in range(1, n_panels)]
    _draw_panels(panels, families, curves, times, [t for t, _ in thumbs])
    for number, (t, rgb) in enumerate(thumbs, start=1):
        ax = fig.add_subplot(grid[0, number - 1])
        ax.imshow(rgb, cmap=None if rgb.ndim == 3 else "gray", vmin=0, vmax=255)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"{number}: {t:.2f} s", fontsize="small")
        h = rgb.shape[0]
        fig.add_artist(ConnectionPatch(xyA=(rgb.shape[1] / 2, h - 0.5), coordsA=ax.transData,
                                       xyB=(t, 1.05), coordsB=panels[0].transData,
                                       color="grey", lw=0.8, alpha=0.7))
        panels[0].annotate(str(number), (t, 1.05), xytext=(2, -9),
                           textcoords="offset points", fontsize="x-small", color="dimgrey")
    if title:
        fig.suptitle(title, fontsize="medium")
    fig.savefig(path, dpi=DPI, format="png")
    plt.close(fig)


def _normalised(q: dict[str, np.ndarray], layers: dict[str, int]) -> dict[str, np.ndarray]:
    """Each region's (F,) Q divided by its top layer, so every curve runs over [0, 1]."""
    curves = {}
    for name, v in q.items():
        k = layers.get(name)
        if not isinstance(k, int) or k < 2:
            raise ValueError(f"layers[{name!r}]: expected an int >= 2, got {k!r}")
        curves[name] = v / (k - 1)
    return curves


def _draw_panels(panels: list[Any], families: dict[str, list[str]],
                 curves: dict[str, np.ndarray], times: np.ndarray, marks: list[float]) -> None:
    """One panel per family of regions: their normalised Q against time, the thumbnails'
    times marked."""
    for ax, (family, names) in zip(panels, families.items(), strict=True):
        for name in names:
            ax.plot(times, curves[name], lw=1.2, label=name)
        ax.set_ylim(-0.05, 1.05)
        ax.set_yticks([0, 0.5, 1])
        ax.set_ylabel(family, fontsize="small")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize="x-small", framealpha=0.7,
                  title=MEANING.get(family), title_fontsize="x-small")
        for t in marks:
            ax.axvline(t, color="grey", ls="--", lw=0.8)
        if ax is not panels[-1]:
            ax.tick_params(labelbottom=False)
    if times.size:
        panels[0].set_xlim(times.min(), times.max() if times.max() > times.min()
                           else times.min() + 1)
    panels[-1].set_xlabel("time, s")


def _family(name: str) -> str:
    """The panel of a region: its name without a ``_left`` / ``_right`` suffix."""
    for side in ("_left", "_right"):
        if name.endswith(side):
            return name[: -len(side)]
    return name


def _thumbnail(i: int, time: float, image: np.ndarray) -> tuple[float, np.ndarray]:
    """(time, RGB or grey image) of one validated thumbnail."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3
                                                           and image.shape[2] == 3)):
        raise ValueError(f"thumbnails[{i}]: expected an (H, W, 3) BGR or (H, W) uint8 image, "
                         f"got {image.shape} {image.dtype}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"thumbnails[{i}]: empty image {image.shape}")
    if not isinstance(time, (int, float, np.number)) or not np.isfinite(time):
        raise ValueError(f"thumbnails[{i}]: time {time!r} is not a finite number of seconds")
    return float(time), image[:, :, ::-1] if image.ndim == 3 else image
