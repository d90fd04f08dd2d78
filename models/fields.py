"""The person model's field checks and the limits they apply, one place for both readers.

A person model is checked twice over the same fields: by its types when it is built in
memory (``models.modelfile``'s ``PersonModel``, ``Region``, ``Area``; ``models.manifest``'s
``ModelInfo``, ``SourceRange``, ``SelfCheck``), and by the manifest reader when it comes from
a file (``models.manifest.parse_manifest``). Both use these checks, so a value is held to the
same limits and refused with the same message either way. Every check raises ``ModelError``
(a ``ValueError``) whose message starts with the field's name, e.g.
``info.frames_used[3]: not strictly increasing``; the file reader prefixes the file and the
member. A file that cannot be read or written at all is a ``ModelFileError`` naming it.

Limits: a region holds 1 to ``MAX_LAYERS`` (64) layers and at most ``MAX_AREAS`` (4)
further areas; a model at most ``MAX_REGIONS`` (32) regions (and coverage states); an image
side is 1 to ``MAX_IMAGE_SIDE`` (4096) pixels; a classification template is
``TEMPLATE_SIZE`` x ``TEMPLATE_SIZE`` (16 x 16). Names (regions, coverage states) match
``[a-z][a-z0-9_]{0,31}``; hashes are 64 lowercase hex digits.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from facewire.protocol.errors import FacewireError

MAX_IMAGE_SIDE = 4096
MAX_LAYERS = 64
MAX_REGIONS = 32
MAX_AREAS = 4
TEMPLATE_SIZE = 16
DESCRIPTOR_SIZE = 128  # dlib's face descriptor (sender.identity)
MAX_DESCRIPTORS = 16
PATCH_REGION = "texture"  # the region a record names for a texture patch (models.patch)

REGION_NAME = re.compile(r"[a-z][a-z0-9_]{0,31}", re.ASCII)
HEX64 = re.compile(r"[0-9a-f]{64}", re.ASCII)


class ModelError(FacewireError, ValueError):
    """A person model's content is invalid; the message names the field."""


class ModelFileError(FacewireError, ValueError):
    """A model file cannot be read or written; the message names the file and the field."""


def type_name(value: object) -> str:
    return type(value).__name__


def check_coverage(value: object) -> dict[str, bool]:
    """The ``coverage`` field: at most ``MAX_REGIONS`` states, names as region names, each
    true or false; raises ``ModelError`` otherwise."""
    if not isinstance(value, dict) or len(value) > MAX_REGIONS:
        raise ModelError(f"coverage: expected an object of at most {MAX_REGIONS} states, "
                         f"got {type_name(value)}")
    for name, covered in value.items():
        if not isinstance(name, str) or not REGION_NAME.fullmatch(name):
            raise ModelError(f"coverage: bad state name {name!r:.40}")
        if not isinstance(covered, bool):
            raise ModelError(f"coverage[{name!r}]: expected true or false, "
                             f"got {type_name(covered)}")
    return dict(value)


def check_keys(value: object, field: str, keys: set[str]) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ModelError(f"{field}: expected an object, got {type_name(value)}")
    missing, unknown = sorted(keys - value.keys()), sorted(value.keys() - keys)
    if missing:
        raise ModelError(f"{field}: missing key {missing[0]!r}")
    if unknown:
        raise ModelError(f"{field}: unknown key {unknown[0]!r:.80}")
    return value


def check_integer(value: object, field: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ModelError(f"{field}: expected an integer, got {type_name(value)}")
    if not low <= value <= high:
        raise ModelError(f"{field}: {value} outside [{low}, {high}]")
    return int(value)


def check_number(value: object, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ModelError(f"{field}: expected a number, got {type_name(value)}")
    number = float(value)
    if not math.isfinite(number):
        raise ModelError(f"{field}: must be finite, got {number}")
    return number


def check_text(value: object, field: str, low: int, high: int) -> str:
    if not isinstance(value, str):
        raise ModelError(f"{field}: expected a string, got {type_name(value)}")
    if not low <= len(value) <= high or not value.isprintable():
        raise ModelError(f"{field}: expected {low} to {high} printable characters")
    return value


def check_region_name(value: object, field: str) -> str:
    if not isinstance(value, str) or not REGION_NAME.fullmatch(value):
        raise ModelError(f"{field}: expected a name matching [a-z][a-z0-9_]{{0,31}}, "
                         f"got {value!r:.40}")
    return value


def check_rect(value: object, field: str) -> tuple[float, float, float, float]:
    if not isinstance(value, (tuple, list)) or len(value) != 4:
        raise ModelError(f"{field}: expected [u0, v0, u1, v1]")
    u0, v0, u1, v1 = (check_number(x, field) for x in value)
    if not (0 <= u0 < u1 <= 1 and 0 <= v0 < v1 <= 1):
        raise ModelError(f"{field}: expected 0 <= u0 < u1 <= 1 and 0 <= v0 < v1 <= 1")
    return (u0, v0, u1, v1)


def check_ndarray(value: object, field: str, dtype: type, ndim: int) -> None:
    if not isinstance(value, np.ndarray):
        raise ModelError(f"{field}: expected a numpy array, got {type_name(value)}")
    if value.dtype != dtype:
        raise ModelError(f"{field}: expected dtype {np.dtype(dtype).name}, got {value.dtype}")
    if value.ndim != ndim:
        raise ModelError(f"{field}: expected {ndim} dimensions, got shape {value.shape}")
