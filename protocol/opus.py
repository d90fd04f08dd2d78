"""The voice codec: Opus (RFC 6716), through the libopus that ships inside PyAV's wheel.

PyAV encodes Opus, but its decoder takes an empty packet for the end of the stream, so it
cannot conceal a lost packet or recover one from the next packet's in-band FEC; libopus's
own ``opus_decode`` does both. So both directions call libopus directly (``ctypes``), the
library PyAV's FFmpeg is linked with (``av.libs/libopus-*.so*``; a system ``libopus`` is the
fallback), so there is one Opus and nothing more to install.

The voice is 48 kHz mono, 16-bit PCM, in frames of ``FRAME_SAMPLES`` (20 ms). The encoder is
set for speech on a lossy link:

- application VOIP and signal VOICE (SILK, or hybrid at higher rates);
- constant bit rate, so every packet of a stream has the same size: ``bitrate * 20 ms / 8``
  bytes (``packet_bytes``), and the voice's share of the link is known before it starts;
- in-band FEC on, tuned for ``loss_percent`` expected loss: packet n may also carry a coarse
  copy of packet n - 1 (SILK's LBRR frame), which the decoder uses when n - 1 is lost and n
  arrived (``Decoder.recover``; ``has_fec`` tells whether a packet carries one). libopus
  spends bits on it only where they leave enough for the speech itself: in wideband from
  about 20 kbit/s at 10 % expected loss, 17 kbit/s at 25 % or more, never at 16 kbit/s or
  under (docs/DESIGN.md section 12). At the default rate, under the voice's 12 kbit/s
  budget, packets carry none and a lost frame is concealed; FEC stays on so that a stream
  given a higher ``--voice-kbps`` gains it;
- bandwidth at most wideband (8 kHz of audio): at these rates a wider band takes bits from
  the speech.

Decoding any byte string either gives ``FRAME_SAMPLES`` samples or raises ``OpusError``;
``Decoder.conceal`` gives a frame of loss concealment (the decoder extrapolates the voice
and fades it), never noise.

ctypes calls the variadic ``opus_*_ctl`` with one ``int`` argument; on the System V x86-64
and AArch64 Linux ABIs an ``int`` passes to a variadic function as to a fixed one.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from functools import cache
from pathlib import Path

import numpy as np

from facewire.protocol.errors import FacewireError

SAMPLE_RATE = 48_000
FRAME_SAMPLES = 960  # 20 ms at 48 kHz
FRAME_S = FRAME_SAMPLES / SAMPLE_RATE
DEFAULT_BITRATE = 9_600  # bit/s; with the packet header the voice stays under 12 kbit/s
MIN_BITRATE = 6_000
MAX_BITRATE = 24_000
MAX_PACKET_BYTES = 1275  # RFC 6716, 3.2.1: the largest frame

_APPLICATION_VOIP = 2048
_SET_BITRATE = 4002
_SET_MAX_BANDWIDTH = 4004
_SET_VBR = 4006
_SET_COMPLEXITY = 4010
_SET_INBAND_FEC = 4012
_SET_PACKET_LOSS_PERC = 4014
_SET_SIGNAL = 4024
_SIGNAL_VOICE = 3001
_BANDWIDTH_WIDEBAND = 1103


class OpusError(FacewireError, ValueError):
    """libopus is missing, refused a setting, or could not decode a packet."""


def packet_bytes(bitrate: int) -> int:
    """The size of every packet of a constant-bit-rate stream at ``bitrate`` bit/s."""
    return bitrate * FRAME_SAMPLES // SAMPLE_RATE // 8


@cache
def _library() -> ctypes.CDLL:
    import av  # noqa: PLC0415 - only to find the folder of the libraries its wheel ships

    bundled = sorted((Path(av.__file__).parent.parent / "av.libs").glob("libopus*.so*"))
    name = str(bundled[0]) if bundled else ctypes.util.find_library("opus")
    if name is None:
        raise OpusError("no libopus: neither PyAV's wheel (av.libs) nor the system has one; "
                        "reinstall with ./install.sh")
    lib = ctypes.CDLL(name)
    handle, int_p = ctypes.c_void_p, ctypes.POINTER(ctypes.c_int)
    pcm_p, bytes_p = ctypes.POINTER(ctypes.c_int16), ctypes.c_char_p
    lib.opus_encoder_create.argtypes = [ctypes.c_int32, ctypes.c_int, ctypes.c_int, int_p]
    lib.opus_encoder_create.restype = handle
    lib.opus_encoder_destroy.argtypes = [handle]
    lib.opus_encoder_ctl.argtypes = [handle, ctypes.c_int, ctypes.c_int]
    lib.opus_encode.argtypes = [handle, pcm_p, ctypes.c_int, bytes_p, ctypes.c_int32]
    lib.opus_encode.restype = ctypes.c_int32
    lib.opus_decoder_create.argtypes = [ctypes.c_int32, ctypes.c_int, int_p]
    lib.opus_decoder_create.restype = handle
    lib.opus_decoder_destroy.argtypes = [handle]
    lib.opus_decode.argtypes = [handle, bytes_p, ctypes.c_int32, pcm_p, ctypes.c_int, ctypes.c_int]
    lib.opus_packet_get_nb_samples.argtypes = [bytes_p, ctypes.c_int32, ctypes.c_int32]
    lib.opus_packet_has_lbrr.argtypes = [bytes_p, ctypes.c_int32]
    lib.opus_strerror.restype = ctypes.c_char_p
    lib.opus_get_version_string.restype = ctypes.c_char_p
    return lib


def version() -> str:
    """libopus's version string, e.g. ``"libopus 1.5.2"``."""
    return _library().opus_get_version_string().decode()


def has_fec(data: bytes) -> bool:
    """Whether the Opus packet ``data`` carries in-band FEC (an LBRR frame) for the frame
    before it; False for a packet that does not parse."""
    return 0 < len(data) <= MAX_PACKET_BYTES and _library().opus_packet_has_lbrr(
        data, len(data)) == 1


def _check(code: int, what: str) -> int:
    if code < 0:
        raise OpusError(f"{what}: {_library().opus_strerror(code).decode()}")
    return code


class Encoder:
    """20-ms frames of 48 kHz mono speech in, constant-size Opus packets out."""

    def __init__(self, bitrate: int = DEFAULT_BITRATE, loss_percent: int = 10) -> None:
        if not MIN_BITRATE <= bitrate <= MAX_BITRATE:
            raise OpusError(f"voice bit rate {bitrate} bit/s is outside "
                            f"{MIN_BITRATE}..{MAX_BITRATE}")
        if not 0 <= loss_percent <= 100:
            raise OpusError(f"expected loss {loss_percent} % is outside 0..100")
        lib = _library()
        error = ctypes.c_int(0)
        self._handle = lib.opus_encoder_create(SAMPLE_RATE, 1, _APPLICATION_VOIP,
                                               ctypes.byref(error))
        _check(error.value, "opus encoder")
        for request, value in ((_SET_BITRATE, bitrate), (_SET_VBR, 0), (_SET_COMPLEXITY, 9),
                               (_SET_INBAND_FEC, 1), (_SET_PACKET_LOSS_PERC, loss_percent),
                               (_SET_SIGNAL, _SIGNAL_VOICE),
                               (_SET_MAX_BANDWIDTH, _BANDWIDTH_WIDEBAND)):
            _check(lib.opus_encoder_ctl(self._handle, request, value), f"opus setting {request}")
        self.bitrate = bitrate
        self._out = ctypes.create_string_buffer(MAX_PACKET_BYTES)

    def encode(self, pcm: np.ndarray) -> bytes:
        """One packet of ``packet_bytes(bitrate)`` bytes.

        Args:
            pcm: (FRAME_SAMPLES,) int16, 20 ms of 48 kHz mono.
        """
        if pcm.shape != (FRAME_SAMPLES,) or pcm.dtype != np.int16:
            raise OpusError(f"a voice frame is ({FRAME_SAMPLES},) int16, got {pcm.shape} "
                            f"{pcm.dtype}")
        frame = np.ascontiguousarray(pcm)
        size = _check(_library().opus_encode(
            self._handle, frame.ctypes.data_as(ctypes.POINTER(ctypes.c_int16)), FRAME_SAMPLES,
            self._out, MAX_PACKET_BYTES), "opus encode")
        return self._out.raw[:size]

    def __del__(self) -> None:
        if getattr(self, "_handle", None):
            _library().opus_encoder_destroy(self._handle)


class Decoder:
    """Opus packets in, 20-ms frames of 48 kHz mono out; concealment and FEC recovery."""

    def __init__(self) -> None:
        lib = _library()
        error = ctypes.c_int(0)
        self._handle = lib.opus_decoder_create(SAMPLE_RATE, 1, ctypes.byref(error))
        _check(error.value, "opus decoder")
        self._pcm = np.zeros(FRAME_SAMPLES, np.int16)

    def _run(self, data: bytes | None, fec: int) -> np.ndarray:
        lib = _library()
        if data is not None:
            if not 0 < len(data) <= MAX_PACKET_BYTES:
                raise OpusError(f"an Opus packet of {len(data)} bytes")
            samples = lib.opus_packet_get_nb_samples(data, len(data), SAMPLE_RATE)
            if samples != FRAME_SAMPLES:
                raise OpusError(f"an Opus packet of {samples} samples where a 20-ms frame "
                                f"has {FRAME_SAMPLES}" if samples > 0 else
                                f"a malformed Opus packet ({lib.opus_strerror(samples).decode()})")
        got = _check(lib.opus_decode(
            self._handle, data, 0 if data is None else len(data),
            self._pcm.ctypes.data_as(ctypes.POINTER(ctypes.c_int16)), FRAME_SAMPLES, fec),
            "opus decode")
        return self._pcm[:got].copy()

    def decode(self, data: bytes) -> np.ndarray:
        """(FRAME_SAMPLES,) int16: the frame of this packet."""
        return self._run(data, 0)

    def recover(self, following: bytes) -> np.ndarray:
        """(FRAME_SAMPLES,) int16: the frame *before* ``following``, lost, rebuilt from its
        in-band FEC (concealment when it carries none). ``decode(following)`` comes next."""
        return self._run(following, 1)

    def conceal(self) -> np.ndarray:
        """(FRAME_SAMPLES,) int16: a frame of loss concealment for a packet never received."""
        return self._run(None, 0)

    def __del__(self) -> None:
        if getattr(self, "_handle", None):
            _library().opus_decoder_destroy(self._handle)
