"""The `slip_monitor` node: prints each slip decision on stdout, one line per change
of state and a heartbeat line every `every_s`, with the capture-to-decision latency."""
from __future__ import annotations

import time
from dataclasses import dataclass

from msgs import SlipState
from nodes.node import Node


@dataclass
class SlipMonitorParams:
    topic: str = "/slip"
    every_s: float = 1.0  # also print while the state does not change (0 = changes only)


class SlipMonitor(Node):
    """Human-readable slip decisions, e.g. ``t=3.20s  SLIP     p=0.97  latency 9.1 ms``."""

    Params = SlipMonitorParams

    def setup(self) -> None:
        self.t0_ns = 0
        self.last_slip: bool | None = None
        self.last_print = 0.0
        self.subscribe(self.params.topic, SlipState, self.on_slip, depth=None)

    def on_slip(self, msg: SlipState) -> None:
        now = time.monotonic()
        self.t0_ns = self.t0_ns or msg.stamp_ns
        changed = msg.slip != self.last_slip
        if not changed and (self.params.every_s <= 0 or now - self.last_print < self.params.every_s):
            return
        self.last_slip, self.last_print = msg.slip, now
        latency_ms = (msg.pub_ns - msg.stamp_ns) / 1e6
        state = "SLIP" if msg.slip else "no slip"
        flag = "" if msg.valid else "  (invalid window)"
        print(f"t={(msg.stamp_ns - self.t0_ns) / 1e9:7.2f}s  {state:8s} p={msg.probability:.2f}  "
              f"latency {latency_ms:5.1f} ms{flag}", flush=True)
