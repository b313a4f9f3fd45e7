"""The forwarder's latched messages: the last one per (topic, publisher node), kept apart once
its publisher is gone.

A ROS latched topic dies with its publisher. Here the forwarder held every latched message until
it stopped, so on a forwarder left running (`fv forwarder`) a recorder, `fv topic echo` or a node
that joined after a session also got that session's camera calibration, tracker reference and node
statuses as if they were live: a bag recorded before the next session carried the earlier camera's
`CameraInfo` as its calibration.

ZeroMQ tells the forwarder that some publisher's connection closed, not which messages were
its. Then the forwarder asks every publisher still connected to send its latched messages again (a
subscription to `nodes.bus.REFRESH` + a number, which `PublisherSocket` answers within its
next publish or `update()`); a cached message that none sends back within `REFRESH_WAIT_S` is a gone
publisher's. It is kept apart (the newest `GONE_KEPT`) and replayed only to subscriptions that
ask for gone publishers' messages (`nodes.bus.GONE`): a respawned tracker resumes its predecessor's
reference that way. A copy that comes back later (a publisher slow to answer) makes it live again,
and so does a new message of that topic and node.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterator

from nodes.bus import GONE, REFRESH

REFRESH_WAIT_S = 1.0  # how long publishers have to answer a refresh (a node's status thread does within 0.2 s)
GONE_KEPT = 1000  # gone publishers' messages kept, the newest


@dataclass
class _Refresh:
    """A request to every connected publisher: its subscription prefix, its end (monotonic s) and the
    envelopes of the latched messages sent since it was made."""

    prefix: bytes
    until_s: float
    answered: set[bytes] = field(default_factory=set)


class LatchedCache:
    """Latched messages ([envelope, header, arrays...] frames) by envelope: `live` (a publisher is
    connected) and `gone`. The forwarder calls `received` for each latched message, `replay` for each
    new subscription, `publisher_left` on each closed publisher connection and `expire` on every
    turn of its loop; the last two return the subscription events to send to the publishers."""

    def __init__(self) -> None:
        self.live: dict[bytes, list[Any]] = {}
        self.gone: dict[bytes, list[Any]] = {}
        self._refresh: _Refresh | None = None
        self._again = False  # a publisher left during the running refresh: another follows it
        self._refreshes = 0

    def received(self, frames: list[Any]) -> bool:
        """Keep a latched message; False when it is a copy of the one kept (same header: seq and
        publish time), which subscribers have had: a publisher's answer to a refresh. One without a
        header frame is not kept (True: forwarded, for subscribers to drop and count as malformed): a
        second such message on one envelope raised IndexError and ended the forwarder."""
        if len(frames) < 2:
            return True
        env = _bytes(frames[0])
        if self._refresh is not None:
            self._refresh.answered.add(env)
        held = self.live.get(env)
        if held is not None and _bytes(held[1]) == _bytes(frames[1]):
            return False
        self.gone.pop(env, None)
        self.live[env] = frames
        return True

    def replay(self, prefix: bytes) -> Iterator[list[Any]]:
        """The messages a new subscription to `prefix` gets: the live ones it matches, or for a
        `GONE` prefix the gone ones, their envelopes flagged `GONE`."""
        if prefix[:1] == GONE:
            for env, frames in self.gone.items():
                if (flagged := GONE + env[1:]).startswith(prefix):
                    yield [flagged, *frames[1:]]
        elif prefix:
            yield from (frames for env, frames in self.live.items() if env.startswith(prefix))

    def publisher_left(self, now_s: float) -> list[bytes]:
        """A publisher's connection closed at `now_s` (monotonic s): a refresh starts, or a second one
        follows the one running (a message answered in it may be the publisher's that has just left)."""
        if self._refresh is not None:
            self._again = True
            return []
        return self._start(now_s)

    def expire(self, now_s: float) -> list[bytes]:
        """At the end of a refresh: the live messages nobody sent again are gone publishers'."""
        done = self._refresh
        if done is None or now_s < done.until_s:
            return []
        for env in [env for env in self.live if env not in done.answered]:
            self.gone[env] = self.live.pop(env)
        while len(self.gone) > GONE_KEPT:
            del self.gone[next(iter(self.gone))]
        self._refresh = None
        events = [b"\x00" + done.prefix]
        if self._again:
            self._again = False
            events += self._start(now_s)
        return events

    def _start(self, now_s: float) -> list[bytes]:
        if not self.live:
            return []
        self._refreshes += 1
        self._refresh = _Refresh(REFRESH + str(self._refreshes).encode(), now_s + REFRESH_WAIT_S)
        return [b"\x01" + self._refresh.prefix]


def _bytes(frame: Any) -> bytes:
    return frame.bytes if hasattr(frame, "bytes") else bytes(frame)
