"""The `slip_monitor` node: prints each slip decision on stdout, one line per change
of state and a heartbeat line every `every_s`, with the capture-to-decision latency.

In a replay the frames' capture stamps are the recorded session's, so "now - stamp" is the
recording's age: with `frames` (the replayed image topics) the latency runs from each frame's
arrival at this monitor to its decision's (the decision's publish time, taken before, was printed
as a negative latency once the monitor read the frame after the slip detector had judged it)."""
from __future__ import annotations

import collections
import time
from dataclasses import dataclass, field

from msgs import Image, SlipState
from nodes.node import Node

ARRIVALS_KEPT = 512  # frames whose arrival times are kept (about 10 s of two cameras at 25 fps)
FRAME_DEPTH = 32  # frames queued unread at most, a bound on memory (a monitor further behind prints "n/a")


@dataclass
class SlipMonitorParams:
    """topic: the slip states printed. every_s: also print while the state does not change (0 =
    changes only). frames: image topics whose frames' arrival times the latency is measured from
    ([] = from the capture stamp; a replay's launch file names the topics it plays)."""

    topic: str = "/slip"
    every_s: float = 1.0
    frames: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.every_s >= 0:  # -1 was taken as 0 without a word
            raise ValueError(f"every_s {self.every_s} must be >= 0 (0 = changes only)")


class SlipMonitor(Node):
    """Human-readable slip decisions, e.g. ``t=3.20s  SLIP     p=0.97  latency 9.1 ms``."""

    Params = SlipMonitorParams
    LIVE_PARAMS = frozenset({"every_s"})  # read per state (`fv param set`)

    def setup(self) -> None:
        self.t0_ns = 0
        self.last_slip: bool | None = None
        self.last_print = 0.0
        self.arrival_ns: collections.OrderedDict[int, int] = collections.OrderedDict()
        for topic in self.params.frames:
            self.subscribe(topic, Image, self.on_frame, depth=FRAME_DEPTH)
        self.subscribe(self.params.topic, SlipState, self.on_slip, depth=None)

    def on_frame(self, msg: Image) -> None:
        """Note when the frame of capture stamp ``msg.stamp_ns`` came (ns since the epoch)."""
        self.arrival_ns[msg.stamp_ns] = time.time_ns()
        while len(self.arrival_ns) > ARRIVALS_KEPT:
            self.arrival_ns.popitem(last=False)

    def latency_text(self, msg: SlipState, received_ns: int) -> str:
        """The decision's latency in ms: from its frame's capture to its publishing or, with ``frames``,
        from its frame's arrival here to its own (``received_ns``, ns since the epoch)."""
        if not self.params.frames:
            return f"latency {(msg.pub_ns - msg.stamp_ns) / 1e6:5.1f} ms"
        arrived = self.arrival_ns.get(msg.stamp_ns)
        return ("latency  n/a (frame not seen)" if arrived is None else
                f"latency {(received_ns - arrived) / 1e6:5.1f} ms")

    def on_slip(self, msg: SlipState) -> None:
        received_ns = time.time_ns()
        now = time.monotonic()
        self.t0_ns = self.t0_ns or msg.stamp_ns
        changed = msg.slip != self.last_slip
        if not changed and (self.params.every_s <= 0 or now - self.last_print < self.params.every_s):
            return
        self.last_slip, self.last_print = msg.slip, now
        state = "SLIP" if msg.slip else "no slip"
        flag = "" if msg.valid else "  (invalid window)"
        print(f"t={(msg.stamp_ns - self.t0_ns) / 1e9:7.2f}s  {state:8s} p={msg.probability:.2f}  "
              f"{self.latency_text(msg, received_ns)}{flag}", flush=True)
