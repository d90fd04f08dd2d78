"""Validation of numpy arrays at a boundary: type, exact dtype, shape and finiteness.

A shape is a tuple of sizes, ``None`` for any size (written ``*`` in messages: ``(*, 3)``).
Each message starts with the field's name, e.g. ``uv: expected shape (*, 2), got (5, 3)``,
and is raised as the caller's own error class.
"""

from __future__ import annotations

import numpy as np


def check_array(name: str, a: object, dtype: type, shape: tuple[int | None, ...],
                error: type[Exception]) -> int:
    """Validate one array: a numpy array of exactly ``dtype`` and ``shape``, finite if float.

    Args:
        name: the field's name, the start of every message (a file may be named in it).
        a: the value to check.
        dtype: the one accepted dtype.
        shape: the sizes, ``None`` for any.
        error: the exception class raised, with the message.

    Returns:
        The array's first dimension.
    """
    if not isinstance(a, np.ndarray):
        raise error(f"{name}: expected a numpy array, got {type(a).__name__}")
    if a.dtype != dtype:
        raise error(f"{name}: expected dtype {np.dtype(dtype).name}, got {a.dtype.name}")
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise error(f"{name}: expected shape {want}, got {a.shape}")
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise error(f"{name}: contains NaN or infinity")
    return a.shape[0]
