"""The voice packet: one 20-ms Opus frame, on the face's packet socket, with a sequence of its own.

Layout, big-endian:

=======  =========  ===========================================================
offset   size       content
=======  =========  ===========================================================
0        1          ``KIND`` (0xA) in the top nibble, 4 reserved bits (0)
1        2          seq: the voice frame's number, mod 2**16
3        N          the Opus packet (``protocol.opus``), 1 .. ``MAX_OPUS_BYTES``
3+N      2          CRC-16/CCITT-FALSE of bytes 0 .. 3+N
=======  =========  ===========================================================

A face packet's top nibble is its protocol version (``protocol.packet.VERSION``, 2), so the
first byte tells the two apart on the socket, in a log and at a relay. Voice frame ``seq``
holds the samples captured from ``origin + seq * 20 ms`` on the sender's clock, where
``origin`` is the voice stream's, announced in the Hello (``protocol.control.Voice``); the
receiver unwraps seq (``unwrap``) and so knows every frame's capture time.

At the default 9.6 kbit/s an Opus packet is 24 bytes and a voice packet 29: 11.6 kbit/s of
payload, under the face's 12 kbit/s budget again. The CRC is what keeps a corrupted packet from
being played: random bytes make a valid Opus packet about one time in eight, and the decoder
would play them as noise; a packet whose CRC fails is dropped and counted. Decoding any byte
string either returns a ``VoicePacket`` or raises ``VoiceError``.
"""

from __future__ import annotations

import binascii
from dataclasses import dataclass

from facewire.protocol.errors import FacewireError
from facewire.protocol.opus import MAX_BITRATE, packet_bytes

KIND = 0xA
HEADER_BYTES = 3
CRC_BYTES = 2
MAX_OPUS_BYTES = packet_bytes(MAX_BITRATE)
MAX_VOICE_BYTES = HEADER_BYTES + MAX_OPUS_BYTES + CRC_BYTES
SEQ_MODULO = 1 << 16


class VoiceError(FacewireError, ValueError):
    """A byte string is not a voice packet.

    Attributes:
        reason: one of ``"size"``, ``"kind"``, ``"reserved"``, ``"crc"``.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class VoicePacket:
    """One voice frame: its number (mod 2**16) and its Opus bytes."""

    seq: int
    opus: bytes


def is_voice(data: bytes) -> bool:
    """Whether a message on the packet socket claims to be a voice packet (its first nibble)."""
    return len(data) > 0 and data[0] >> 4 == KIND


def encode(packet: VoicePacket) -> bytes:
    """The packet's bytes (``HEADER_BYTES + len(opus) + CRC_BYTES``)."""
    if not 0 <= packet.seq < SEQ_MODULO:
        raise VoiceError("seq", f"voice seq {packet.seq} outside 0..{SEQ_MODULO - 1}")
    if not 0 < len(packet.opus) <= MAX_OPUS_BYTES:
        raise VoiceError("size", f"an Opus packet of {len(packet.opus)} bytes, "
                                 f"at most {MAX_OPUS_BYTES}")
    body = bytes([KIND << 4]) + packet.seq.to_bytes(2, "big") + packet.opus
    return body + binascii.crc_hqx(body, 0xFFFF).to_bytes(2, "big")


def decode(data: bytes) -> VoicePacket:
    """The packet in ``data``.

    Raises:
        VoiceError: too short or too long, not a voice packet, reserved bits set, bad CRC.
    """
    if not HEADER_BYTES + 1 + CRC_BYTES <= len(data) <= MAX_VOICE_BYTES:
        raise VoiceError("size", f"voice packet of {len(data)} bytes, expected "
                                 f"{HEADER_BYTES + 1 + CRC_BYTES}..{MAX_VOICE_BYTES}")
    if data[0] >> 4 != KIND:
        raise VoiceError("kind", f"first nibble {data[0] >> 4}, a voice packet's is {KIND}")
    if data[0] & 0x0F:
        raise VoiceError("reserved", "voice packet rejected: reserved bits set")
    if binascii.crc_hqx(data[:-CRC_BYTES], 0xFFFF) != int.from_bytes(data[-CRC_BYTES:], "big"):
        raise VoiceError("crc", "voice packet CRC mismatch")
    return VoicePacket(int.from_bytes(data[1:3], "big"), bytes(data[HEADER_BYTES:-CRC_BYTES]))


def unwrap(seq: int, last: int | None) -> int:
    """The frame number nearest ``last`` (an unwrapped number) whose value mod 2**16 is
    ``seq``; ``seq`` itself when there is no ``last``."""
    if last is None:
        return seq
    delta = (seq - last) % SEQ_MODULO
    if delta >= SEQ_MODULO // 2:
        delta -= SEQ_MODULO
    return last + delta
