"""StampOrder: several inputs' items handed on in one stamp order whatever order they arrive in, a silent
input waited for at most wait_s, a stopped one not at all, and a restart handed on and started afresh."""
from __future__ import annotations

import numpy as np
import pytest

from fv_algos.stamp_order import StampOrder

MS = 1_000_000  # ns


def _feed(order: StampOrder, arrivals: list[tuple[str, int]], step_s: float = 0.001) -> list[tuple[str, int]]:
    """Push (input, stamp in ms) items one `step_s` apart (the item is its stamp); what was handed on."""
    out = []
    for k, (name, stamp_ms) in enumerate(arrivals):
        out += order.push(name, stamp_ms * MS, stamp_ms, k * step_s)
    return out


def _interleavings(streams: dict[str, list[int]], rng: np.random.Generator) -> list[tuple[str, int]]:
    """One random arrival order of the streams, each kept in its own order."""
    left = {name: list(stamps) for name, stamps in streams.items()}
    out = []
    while any(left.values()):
        name = rng.choice([n for n, s in left.items() if s])
        out.append((name, left[name].pop(0)))
    return out


def test_any_arrival_order_gives_one_stamp_order() -> None:
    """Two fingers' states at 25 Hz, 13 ms apart, arriving in 50 random orders (each finger's own kept)."""
    streams = {"left": list(range(0, 800, 40)), "right": list(range(13, 800, 40))}
    rng = np.random.default_rng(0)
    results = set()
    for _ in range(50):
        order = StampOrder(["left", "right"], wait_s=0.5, stale_after_s=1.0)
        out = _feed(order, _interleavings(streams, rng))
        assert order.counters == {"waited": 0, "late": 0, "restarts": 0}
        results.add(tuple(out))
    assert len(results) == 1
    (out,) = results
    stamps = [s for _, s in out]
    assert stamps == sorted(stamps) and len(out) == 39  # all but right's last: left may still send before it
    assert out[:3] == (("left", 0), ("right", 13), ("left", 40))


def test_equal_stamps_go_in_the_order_of_the_inputs() -> None:
    for arrivals in ([("b", 0), ("a", 0), ("a", 40), ("b", 40)], [("a", 0), ("b", 0), ("b", 40), ("a", 40)]):
        order = StampOrder(["a", "b"], wait_s=0.5, stale_after_s=1.0)
        assert _feed(order, arrivals) == [("a", 0), ("b", 0), ("a", 40), ("b", 40)]


def test_an_item_waits_for_a_silent_input_at_most_wait_s() -> None:
    order = StampOrder(["a", "b"], wait_s=0.2, stale_after_s=1.0)
    assert order.push("b", 0, "b0", 0.0) == []  # a has not started: it may send an earlier item
    assert order.push("a", 5 * MS, "a5", 0.01) == [("b", "b0")]
    assert order.push("a", 45 * MS, "a45", 0.05) == []  # b may still send one stamped before a5
    assert order.due(0.20) == []
    assert order.due(0.211) == [("a", "a5")] and order.counters["waited"] == 1
    assert order.due(0.251) == [("a", "a45")] and order.held() == 0
    assert order.push("b", 40 * MS, "b40", 0.26) == [("b", "b40")]  # late: handed on at once, counted
    assert order.counters["late"] == 1


def test_a_stopped_input_is_not_waited_for() -> None:
    order = StampOrder(["a", "b"], wait_s=0.5, stale_after_s=1.0)
    _feed(order, [("a", 0), ("b", 1)])
    assert order.push("a", 40 * MS, "a40", 0.9) == [("b", 1)]  # b sent 0.9 s ago: still waited for
    assert order.due(1.002) == [("a", "a40")] and order.counters["waited"] == 0  # b silent for over 1 s: stale
    assert order.push("a", 80 * MS, "a80", 1.1) == [("a", "a80")]


def test_an_input_that_never_starts_is_waited_for_stale_after_s() -> None:
    order = StampOrder(["a", "b"], wait_s=2.0, stale_after_s=1.0)
    assert order.push("a", 0, "a0", 0.0) == []
    assert order.due(0.99) == []
    assert order.due(1.01) == [("a", "a0")]
    assert order.push("a", 40 * MS, "a40", 1.05) == [("a", "a40")]
    assert order.counters["waited"] == 0


def test_stamps_going_back_hand_on_what_is_held_and_start_afresh() -> None:
    """A recording played again: each input's stamps go back to its start."""
    order = StampOrder(["a", "b"], wait_s=0.5, stale_after_s=1.0)
    assert _feed(order, [("a", 0), ("b", 10), ("a", 40), ("b", 50), ("a", 80)]) == [("a", 0), ("b", 10), ("a", 40),
                                                                                    ("b", 50)]
    assert order.push("a", 0, "a0 again", 0.1) == [("a", 80)]  # what was held, then afresh: b awaited again
    assert order.counters["restarts"] == 1 and order.held() == 1
    assert order.push("b", 10 * MS, "b10 again", 0.11) == [("a", "a0 again")]
    assert order.push("a", 40 * MS, "a40 again", 0.12) == [("b", "b10 again")]
    assert order.counters == {"waited": 0, "late": 0, "restarts": 1}


def test_flush_hands_on_everything_held_in_order() -> None:
    order = StampOrder(["a", "b"], wait_s=0.5, stale_after_s=1.0)
    _feed(order, [("a", 40), ("a", 0)])  # a's stamps went back: a restart
    _feed(order, [("a", 80), ("a", 120)])
    assert order.flush() == [("a", 0), ("a", 80), ("a", 120)] and order.held() == 0


@pytest.mark.parametrize("args, message", [((["a", "a"], 0.5, 1.0), "different names"),
                                           (([], 0.5, 1.0), "different names"),
                                           ((["a", "b"], 0.0, 1.0), "wait_s 0.0"),
                                           ((["a", "b"], float("inf"), 1.0), "wait_s inf"),
                                           ((["a", "b"], 0.5, float("nan")), "stale_after_s nan")])
def test_bad_arguments_are_refused(args: tuple, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        StampOrder(*args)
