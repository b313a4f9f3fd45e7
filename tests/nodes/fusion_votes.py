"""Driving a `slip_fusion` node without a bus: its clocks set to each state's arrival, its votes collected."""
from __future__ import annotations

from msgs import SlipState
from nodes.slip_fusion import SlipFusion

S = 1_000_000_000  # ns


def arrive(node: SlipFusion, topic: str, state: SlipState, late_s: float = 0.0) -> None:
    """`state` arrives on `topic` `late_s` after its capture stamp, on the node's clocks (the monotonic one
    in s, the wall clock in ns, both reading the stamps' time)."""
    node.clock = lambda: state.stamp_ns / S + late_s
    node.wall_clock = lambda: state.stamp_ns + int(late_s * S)
    node.on_state(topic, state)


def fused(params: dict, arrivals: list[tuple[str, SlipState, float]]) -> tuple[list[SlipState], dict[str, int]]:
    """The votes a fusion with `params` publishes for (input, state, late_s) arriving in that order (before and
    at its close), and its counters."""
    node = SlipFusion("slip_fusion", params)
    out: list[SlipState] = []
    try:
        node.setup()
        node.pub.publish = out.append
        for topic, state, late_s in arrivals:
            arrive(node, topic, state, late_s)
    finally:
        node.close()
    return out, dict(node.counters)
