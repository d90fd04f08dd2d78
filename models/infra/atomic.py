"""Atomic file writes: a file is either its old content or its new content, never half.

The bytes go to a temporary file in the target's folder (a random name, created exclusively),
are flushed to disk, and the file is then renamed over the target (``os.replace``, atomic on
POSIX within one file system); the folder is flushed too, so the rename survives a crash. On
any failure the temporary file is removed and the target is left as it was.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path


def write_atomically(target: str | os.PathLike[str], data: bytes, mode: int = 0o666) -> None:
    """Replace ``target`` with ``data`` atomically (module docstring).

    Args:
        target: the file to write; its folder must exist.
        data: the new content.
        mode: permission bits of a new file (before the umask).

    Raises:
        OSError: the file cannot be written (the target is unchanged).
    """
    target = Path(target)
    tmp = target.with_name(f".{target.name}.{secrets.token_hex(8)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    folder = os.open(target.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)
