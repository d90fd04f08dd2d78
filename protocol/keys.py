"""CURVE keys for encrypted, authenticated links (ZeroMQ's CurveZMQ, keys as pyzmq writes them).

A key folder, made by ``facewire keys generate DIR``, holds this host's pair and the public
keys it trusts::

    DIR/id.key            this host's public key (give it to the peer)
    DIR/id.key_secret     this host's secret key (never leaves the host)
    DIR/authorized/*.key  peers' public keys: on the sender, every receiver allowed in;
                          on a receiver, the one sender it trusts

The sender (server) accepts only clients whose public key is in its ``authorized`` folder;
a receiver (client) connects only to the server whose key is in its own.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import zmq.auth

from facewire.protocol.errors import FacewireError


class KeyFileError(FacewireError, ValueError):
    """A key folder is missing or malformed; the message names the file."""


@dataclass(frozen=True)
class CurveServer:
    public: bytes
    secret: bytes
    authorized: Path


@dataclass(frozen=True)
class CurveClient:
    public: bytes
    secret: bytes
    server_public: bytes


def generate_keys(folder: str | os.PathLike[str], name: str = "id") -> tuple[Path, Path]:
    """Make a key pair ``folder/name.key`` and ``folder/name.key_secret``, and ``authorized/``.

    Refuses to overwrite an existing pair. The secret key's file is created readable by its
    owner only (0600) before the key is written into it.
    """
    folder = Path(folder)
    secret_path = folder / f"{name}.key_secret"
    (folder / "authorized").mkdir(parents=True, exist_ok=True)
    try:  # created 0600 before the key is written into it (pyzmq keeps an existing file's mode)
        os.close(os.open(secret_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except FileExistsError:
        raise KeyFileError(f"{secret_path}: already exists; not overwriting") from None
    public, secret = zmq.auth.create_certificates(folder, name)
    return Path(public), Path(secret)


def server_keys(folder: str | os.PathLike[str]) -> CurveServer:
    """The sender's keys and the folder of receivers it accepts."""
    folder = Path(folder)
    public, secret = _pair(folder)
    authorized = folder / "authorized"
    if not authorized.is_dir():
        raise KeyFileError(f"{authorized}: missing (put receivers' public keys there)")
    return CurveServer(public, secret, authorized)


def client_keys(folder: str | os.PathLike[str]) -> CurveClient:
    """A receiver's keys and the public key of the one sender it trusts."""
    folder = Path(folder)
    public, secret = _pair(folder)
    servers = sorted((folder / "authorized").glob("*.key"))
    if len(servers) != 1:
        raise KeyFileError(f"{folder / 'authorized'}: expected exactly one sender public key "
                        f"(*.key), found {len(servers)}")
    return CurveClient(public, secret, _load(servers[0])[0])


def _pair(folder: Path) -> tuple[bytes, bytes]:
    public, secret = _load(folder / "id.key_secret")
    if secret is None:
        raise KeyFileError(f"{folder / 'id.key_secret'}: holds no secret key")
    return public, secret


def _load(path: Path) -> tuple[bytes, bytes | None]:
    if not path.is_file():
        raise KeyFileError(f"{path}: missing (make keys with 'facewire keys generate DIR')")
    try:
        return zmq.auth.load_certificate(path)
    except (ValueError, OSError) as exc:
        raise KeyFileError(f"{path}: not a CURVE key file: {exc}") from None
