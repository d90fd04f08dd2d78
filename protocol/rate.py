"""The packet rate contract: how often packets go out, and the bit rate that costs.

A stream sends one fixed-size packet (``protocol.packet.PACKET_BYTES``, 43 bytes in version 2)
per slot of ``1 / rate_hz`` seconds, so its payload bit rate is

    payload kbit/s = PACKET_BYTES * 8 * rate_hz / 1000          (``kbps``, ``payload_kbps``)

The design's rate is ``NOMINAL_HZ`` = 30 Hz: 10.32 kbit/s. The paper's budget,
``PAYLOAD_LIMIT_KBPS`` = 12 kbit/s, applies to the payload (the packets' own bytes, no
transport framing, as in the paper), so a stream stays within it up to
``PAYLOAD_LIMIT_HZ`` = 12000 / (8 * 43) = 34.88 Hz.

A stream's rate is in [``MIN_RATE_HZ``, ``MAX_RATE_HZ``] (what a Hello may announce): a slot
longer than a second is no live stream, and a rate near zero would put a receiver's next slot
at an absurd time. ``stream_rate`` puts a source's frame rate into that range.
"""

from __future__ import annotations

import math

from facewire.protocol.packet import PACKET_BYTES

NOMINAL_HZ = 30.0
PAYLOAD_LIMIT_KBPS = 12.0
MIN_RATE_HZ = 1.0
MAX_RATE_HZ = 1000.0
PAYLOAD_LIMIT_HZ = PAYLOAD_LIMIT_KBPS * 1000 / (PACKET_BYTES * 8)


def kbps(message_bytes: float, rate_hz: float) -> float:
    """Bit rate in kbit/s of messages of ``message_bytes`` bytes sent ``rate_hz`` times a
    second."""
    return message_bytes * 8 * rate_hz / 1000


def payload_kbps(rate_hz: float) -> float:
    """The payload bit rate in kbit/s of a stream at ``rate_hz``."""
    return kbps(PACKET_BYTES, rate_hz)


def stream_rate(source_hz: float) -> float:
    """A source's frame rate put into [``MIN_RATE_HZ``, ``MAX_RATE_HZ``]; ``NOMINAL_HZ`` when
    the source states none (0 or not finite)."""
    if not (math.isfinite(source_hz) and source_hz > 0):
        return NOMINAL_HZ
    return float(min(max(source_hz, MIN_RATE_HZ), MAX_RATE_HZ))


def over_budget_warning(rate_hz: float) -> str | None:
    """One line saying that a stream at ``rate_hz`` would put the payload at or over
    ``PAYLOAD_LIMIT_KBPS``; None when it stays under."""
    if payload_kbps(rate_hz) < PAYLOAD_LIMIT_KBPS:
        return None
    return (f"warning: --rate {rate_hz:g} puts the payload at {payload_kbps(rate_hz):.2f} kbit/s, "
            f"over the {PAYLOAD_LIMIT_KBPS:g} kbit/s budget (under {PAYLOAD_LIMIT_HZ:.2f} Hz "
            f"keeps it)")
