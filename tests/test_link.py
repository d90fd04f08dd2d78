"""``receiver.link.SenderLink``'s signs that a recheck of the Hello is due, on a real control
socket (no sender behind it: the signs are judged without asking)."""

from __future__ import annotations

import dataclasses

import pytest

from facewire.protocol.clock import MAX_LAG_S
from facewire.protocol.control import Camera, Hello
from facewire.protocol.transport import free_loopback_endpoint
from facewire.receiver.link import RECHECK_EVERY_S, SenderLink

HELLO = Hello("ab" * 32, 5000, 30.0, Camera(600.0, 600.0, 320.0, 240.0, 640, 480), (),
              clock_origin_s=100.0)


@pytest.fixture
def link():
    link = SenderLink(free_loopback_endpoint(), None)
    link.take(HELLO)
    yield link
    link.close()


def test_a_packet_later_than_the_senders_lag_makes_a_recheck_due(link: SenderLink) -> None:
    """A sender behind its schedule moves its origin by more than ``MAX_LAG_S`` each time;
    its packets keep coming with consecutive seqs, so their lateness by the old origin is the
    only sign."""
    assert not link.note_lateness(0.03, 10.0) and not link.due  # on time
    assert not link.note_lateness(MAX_LAG_S, 10.0) and not link.due
    assert link.note_lateness(MAX_LAG_S + 0.1, 10.0) and link.due


def test_a_long_path_asks_once_and_again_only_as_its_lateness_grows(link: SenderLink) -> None:
    """The Hello answered the same (the origin did not move: the path is that slow): the same
    lateness asks no more; a lateness grown by ``MAX_LAG_S`` more asks again; a Hello with a
    new origin starts the count again."""
    now = 10.0
    assert link.note_lateness(0.8, now)
    link.due = False  # asked, answered the same
    link.take(HELLO)
    for k in range(100):
        assert not link.note_lateness(0.8 + MAX_LAG_S * 0.9, now + k)
    assert not link.due
    now += 100
    assert link.note_lateness(0.8 + MAX_LAG_S * 1.1, now)
    link.due = False
    link.take(dataclasses.replace(HELLO, clock_origin_s=101.3))  # the moved origin taken
    assert not link.note_lateness(0.05, now + RECHECK_EVERY_S)
    assert link.note_lateness(MAX_LAG_S + 0.05, now + RECHECK_EVERY_S)


def test_a_sender_far_behind_is_asked_at_most_every_recheck_period(link: SenderLink) -> None:
    """A sender that moves its origin every few frames is not asked at every move."""
    assert link.note_lateness(MAX_LAG_S + 0.1, 10.0)
    link.due = False
    link.take(dataclasses.replace(HELLO, clock_origin_s=100.6))
    assert not link.note_lateness(MAX_LAG_S + 0.1, 10.0 + RECHECK_EVERY_S / 2)
    assert link.note_lateness(MAX_LAG_S + 0.1, 10.0 + RECHECK_EVERY_S)
