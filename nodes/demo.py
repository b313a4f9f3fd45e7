"""Two small nodes to try the bus: `talker` publishes SlipState at a fixed rate and
`listener` logs what it receives (also used by the bus tests)."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

from msgs import SlipState
from nodes.node import Node


@dataclass
class TalkerParams:
    topic: str = "/chatter"
    rate_hz: float = 10.0
    latched: bool = False

    def __post_init__(self) -> None:
        if self.rate_hz <= 0:
            raise ValueError(f"rate_hz {self.rate_hz} must be > 0")


class Talker(Node):
    """Publishes a slowly varying slip probability on `topic` at `rate_hz`."""

    Params = TalkerParams

    def setup(self) -> None:
        self.pub = self.publisher(self.params.topic, SlipState, latched=self.params.latched)
        self.timer(1.0 / self.params.rate_hz, self.tick)

    def tick(self) -> None:
        p = 0.5 + 0.5 * math.sin(time.monotonic())
        self.pub.publish(SlipState(stamp_ns=time.time_ns(), probability=p, slip=p > 0.5))


@dataclass
class ListenerParams:
    topic: str = "/chatter"
    depth: int = 10
    sleep_s: float = 0.0


class Listener(Node):
    """Logs each message on `topic` (sleeping `sleep_s` per message to act slow)."""

    Params = ListenerParams

    def setup(self) -> None:
        self.received = 0
        self.subscribe(self.params.topic, None, self.on_msg, depth=self.params.depth)

    def on_msg(self, msg) -> None:
        self.received += 1
        self.counters["received"] = self.received
        self.log.info("%s seq=%d", msg.TYPE, msg.seq)
        if self.params.sleep_s:
            time.sleep(self.params.sleep_s)
