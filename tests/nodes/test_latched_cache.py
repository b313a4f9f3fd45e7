"""The forwarder's latched messages: live while a publisher sends them back when asked, then kept
apart for the subscriptions that ask for gone publishers' messages."""
from __future__ import annotations

from nodes.bus import GONE, REFRESH, envelope
from nodes.latched_cache import GONE_KEPT, REFRESH_WAIT_S, LatchedCache


def _message(topic: str, node: str, seq: int) -> list[bytes]:
    return [envelope(topic, node, True), f"header {seq}".encode(), b"array"]


def test_a_message_nobody_sends_back_is_a_gone_publisher_s() -> None:
    cache = LatchedCache()
    old, live = _message("/camera/info", "old_camera", 0), _message("/camera/info", "camera", 0)
    assert cache.received(old) and cache.received(live)
    assert not cache.received(list(live)), "a copy of the message kept is not forwarded again"
    assert cache.publisher_left(10.0) == [b"\x01" + REFRESH + b"1"]
    assert not cache.received(list(live))  # the publisher still connected answers
    assert cache.expire(10.0 + REFRESH_WAIT_S / 2) == []
    assert cache.expire(10.0 + REFRESH_WAIT_S) == [b"\x00" + REFRESH + b"1"]
    assert list(cache.replay(b"L/camera/info\0")) == [live]
    assert list(cache.replay(b"L")) == [live] and list(cache.replay(b"")) == []
    assert list(cache.replay(GONE + b"/camera/info\0")) == [[GONE + old[0][1:], *old[1:]]]
    assert list(cache.replay(GONE + b"/camera/info\0camera")) == [], "old_camera is not camera"


def test_a_late_answer_or_a_new_message_makes_it_live_again() -> None:
    cache = LatchedCache()
    slow = _message("/status", "slow", 3)
    cache.received(slow)
    cache.publisher_left(0.0)
    cache.expire(REFRESH_WAIT_S)
    assert list(cache.replay(b"L")) == []
    assert cache.received(list(slow)), "a late answer is forwarded: subscribers that joined since lack it"
    assert list(cache.replay(b"L")) == [slow] and list(cache.replay(GONE)) == []
    cache.publisher_left(5.0)
    cache.expire(5.0 + REFRESH_WAIT_S)
    newer = _message("/status", "slow", 4)
    assert cache.received(newer) and list(cache.replay(b"L")) == [newer] and list(cache.replay(GONE)) == []


def test_a_publisher_leaving_during_a_refresh_starts_another_after_it() -> None:
    """A message answered in a refresh may be that of a publisher that leaves before its end: a second
    refresh follows, so that it is found gone too."""
    cache = LatchedCache()
    a, b = _message("/a", "a", 0), _message("/b", "b", 0)
    cache.received(a)
    cache.received(b)
    cache.publisher_left(0.0)
    cache.received(list(a))
    cache.received(list(b))  # b answers, then leaves
    assert cache.publisher_left(0.5) == []
    assert cache.expire(REFRESH_WAIT_S) == [b"\x00" + REFRESH + b"1", b"\x01" + REFRESH + b"2"]
    assert sorted(cache.live) == sorted([a[0], b[0]])
    cache.received(list(a))
    cache.expire(2 * REFRESH_WAIT_S)
    assert list(cache.live) == [a[0]] and list(cache.gone) == [b[0]]


def test_gone_messages_are_kept_up_to_a_bound_the_newest() -> None:
    cache = LatchedCache()
    for k in range(GONE_KEPT + 5):
        cache.received(_message("/status", f"tool_{k}", 0))
    cache.publisher_left(0.0)
    cache.expire(REFRESH_WAIT_S)
    assert len(cache.gone) == GONE_KEPT and envelope("/status", f"tool_{GONE_KEPT + 4}", True) in cache.gone
    assert envelope("/status", "tool_4", True) not in cache.gone
    assert cache.publisher_left(1.0) == [], "nothing live: nothing to ask"


def test_a_latched_message_without_a_header_is_forwarded_not_kept() -> None:
    """Two latched messages of one envelope and no header frame (published by hand) ended the
    forwarder with an IndexError: every node lost the bus until the launcher restarted it."""
    cache = LatchedCache()
    bare = [envelope("/slip", "by_hand", True)]
    assert cache.received(list(bare)) and cache.received(list(bare))
    assert cache.live == {} and list(cache.replay(b"L")) == []
