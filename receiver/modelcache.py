"""The render host's model cache: person models stored under their sha256, verified both ways.

A receiver without ``--model`` learns the model's sha256 from the sender's Hello and looks
here before fetching anything, so a later run, or another receiver on the same host, never
downloads the same model again.

Layout: ``FOLDER/<sha256>.fwm``, the model file's exact bytes (64 lowercase hex digits, the
sha256 of those bytes, as ``models.modelfile`` defines a model's id). ``FOLDER`` is
``$FACEWIRE_CACHE`` when set, else ``~/.cache/facewire/models``; it is created on the first
write, private to the user (mode 0700, files 0600: a model is a person's face).

Reading (``ModelCache.get``): the file is read whole (at most ``MAX_FILE_BYTES``), hashed
and decoded (``models.modelfile.load_model_bytes``). A file that no longer hashes to its
name (disk damage, an edit) or that does not decode is refused with ``ModelCacheError``:
the receiver fetches the model again and ``put`` replaces the file. A refused file is not
deleted, since another receiver may be replacing it at that moment.

Writing (``verify_model``, then ``ModelCache.put``): fetched bytes must hash to the
announced sha256 and decode as a model before anything is written; ``put`` takes the
decoded model and checks it is the model of those bytes. The bytes go to a temporary file
in the cache folder (``models.infra.atomic``: ``.<sha256>.fwm.<random>.tmp``, created
exclusively), are flushed to disk (fsync), and are renamed over ``<sha256>.fwm`` with
``os.replace``; the folder is then fsynced so the rename survives a crash.

Concurrency: no lock is needed. A rename within one file system is atomic (POSIX
``rename(2)``): a reader sees no file or a whole one, never a part, and a crash leaves at
most a stray temporary file, never a short ``.fwm``. Two receivers that fetch the same model
at the same moment each write their own temporary file and the last rename wins, with the
same bytes; a receiver started after the first write has finished finds the file and
fetches nothing. (Only receivers that start together, with an empty cache, may both fetch
the model once.)
"""

from __future__ import annotations

import hashlib
import os
import re
import stat
from pathlib import Path

from facewire.models.infra.atomic import write_atomically
from facewire.models.modelfile import MAX_FILE_BYTES, PersonModel, load_model_bytes
from facewire.protocol.errors import FacewireError

ENV_FOLDER = "FACEWIRE_CACHE"
SUFFIX = ".fwm"
_HEX64 = re.compile(r"[0-9a-f]{64}", re.ASCII)


class ModelCacheError(FacewireError, ValueError):
    """A cached model is refused, fetched bytes are not the announced model, or the cache
    cannot be written; the message names the file or the sha256."""


def default_folder() -> Path:
    """``$FACEWIRE_CACHE`` if set (and not empty), else ``~/.cache/facewire/models``."""
    env = os.environ.get(ENV_FOLDER)
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "facewire" / "models"


def verify_model(data: bytes, sha256: str, where: str = "<fetched model>") -> PersonModel:
    """Check that ``data`` is the model with id ``sha256`` and decode it.

    Args:
        data: the bytes of a ``.fwm`` file, e.g. as reassembled from the network.
        sha256: the announced model id, 64 lowercase hex digits.
        where: names the source in error messages.

    Returns:
        The decoded model (its ``sha256`` is ``sha256``).

    Raises:
        ModelCacheError: ``sha256`` is malformed, or the bytes hash to something else.
        ModelFileError: the bytes hash right but are not a valid model file.
    """
    _check_sha(sha256)
    digest = hashlib.sha256(data).hexdigest()
    if digest != sha256:
        raise ModelCacheError(f"{where}: its bytes hash to {digest[:16]}..., not the announced "
                              f"{sha256[:16]}...")
    return load_model_bytes(bytes(data), where)


class ModelCache:
    """Models on disk by sha256 (module docstring).

    Args:
        folder: the cache folder; ``default_folder()`` when None. Not created until a write.

    Attributes:
        folder: the cache folder.
    """

    def __init__(self, folder: str | os.PathLike[str] | None = None) -> None:
        self.folder = default_folder() if folder is None else Path(folder)

    def path(self, sha256: str) -> Path:
        """Where the model with this id is (or would be) cached.

        Raises:
            ModelCacheError: ``sha256`` is not 64 lowercase hex digits (never a path).
        """
        _check_sha(sha256)
        return self.folder / f"{sha256}{SUFFIX}"

    def get(self, sha256: str) -> PersonModel | None:
        """The cached model with this id, or None when it is not cached.

        Raises:
            ModelCacheError: a cached file exists but is refused: unreadable, too large, not
                hashing to its name, or not a valid model (the message names the file).
        """
        path = self.path(sha256)
        try:
            with open(path, "rb") as f:
                info = os.fstat(f.fileno())
                if not stat.S_ISREG(info.st_mode):
                    raise ModelCacheError(f"{path}: not a regular file; refused")
                if info.st_size > MAX_FILE_BYTES:
                    raise ModelCacheError(f"{path}: {info.st_size} bytes, more than a model "
                                          f"may have; refused")
                data = f.read(MAX_FILE_BYTES + 1)
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise ModelCacheError(f"{path}: cannot read ({exc.strerror or exc}); "
                                  f"refused") from None
        digest = hashlib.sha256(data).hexdigest()
        if digest != sha256:
            raise ModelCacheError(f"{path}: damaged (its bytes hash to {digest[:16]}...); "
                                  f"refused")
        try:
            return load_model_bytes(data, str(path))
        except ValueError as exc:
            raise ModelCacheError(f"{exc}; refused") from None

    def put(self, data: bytes, model: PersonModel) -> Path:
        """Cache a verified model's bytes atomically (module docstring).

        Args:
            data: the model file's bytes.
            model: ``verify_model(data, ...)``: the model decoded from exactly these bytes.

        Returns:
            The cached file's path.

        Raises:
            ModelCacheError: ``model`` is not the model of ``data``, or the file cannot be
                written (names it).
        """
        if not isinstance(model, PersonModel) or not model.sha256:
            raise ModelCacheError("put: expected the PersonModel decoded from the bytes "
                                  "(verify_model)")
        if len(data) != model.file_bytes or hashlib.sha256(data).hexdigest() != model.sha256:
            raise ModelCacheError(f"put: the bytes are not those of model "
                                  f"{model.sha256[:16]}...")
        target = self.path(model.sha256)
        try:
            self.folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            write_atomically(target, data, 0o600)
        except OSError as exc:
            raise ModelCacheError(f"{target}: cannot write ({exc.strerror or exc})") from None
        return target


def _check_sha(sha256: object) -> None:
    if not isinstance(sha256, str) or not _HEX64.fullmatch(sha256):
        raise ModelCacheError(f"model sha256: expected 64 lowercase hex digits, got "
                              f"{sha256!r:.80}")
