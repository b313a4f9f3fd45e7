"""slip_fusion: both fingers' vote after every state, never a mix of grasps, a stopped camera left
out and named, and bad params refused."""
from __future__ import annotations

import numpy as np
import pytest

from fv_algos.camera_vote import camera_vote
from msgs import SlipState
from nodes.slip_fusion import SlipFusion

S = 1_000_000_000  # ns


def _state(stamp_s: float, p: float, grasp_s: float = 0.0, valid: bool = True) -> SlipState:
    return SlipState(stamp_ns=int(stamp_s * S), probability=p, slip=p >= 0.5, model="gelsight_online", valid=valid,
                     window_stamps_ns=np.array([int(grasp_s * S), int(stamp_s * S)], np.int64))


def _arrive(node: SlipFusion, topic: str, state: SlipState, late_s: float = 0.0) -> None:
    """`state` arrives on `topic` `late_s` after its capture stamp, on the node's clocks (the monotonic one
    in s, the wall clock in ns, both reading the stamps' time)."""
    node.clock = lambda: state.stamp_ns / S + late_s
    node.wall_clock = lambda: state.stamp_ns + int(late_s * S)
    node.on_state(topic, state)


@pytest.fixture
def fusion():
    node = SlipFusion("slip_fusion", {})
    published: list[SlipState] = []
    node.setup()
    node.pub.publish = published.append
    yield node, published
    node.close()


def test_every_state_publishes_the_vote_of_both_fingers(fusion) -> None:
    node, out = fusion
    _arrive(node, "/left/slip", _state(0.04, 0.3))
    assert out[0].probability == pytest.approx(0.3) and node.state == "ok"  # right's first frame is due
    _arrive(node, "/right/slip", _state(0.05, 0.9))
    assert out[1].probability == pytest.approx(camera_vote([0.3, 0.9])) and node.state == "ok"
    _arrive(node, "/left/slip", _state(0.08, 0.8))
    assert out[2].probability == pytest.approx(camera_vote([0.8, 0.9])) and out[2].slip
    assert out[2].stamp_ns == int(0.08 * S) and list(out[2].window_stamps_ns) == [0, int(0.08 * S)]
    assert node.counters["voted"] == 3 and node.counters["alone"] == 1


def test_after_a_reset_a_finger_still_on_the_earlier_grasp_is_left_out(fusion) -> None:
    """Right's last state is from before left's new grasp: its reset frame is due, which is no fault. Still
    on the earlier grasp 1 s on (a camera that missed the reset), it is named in the warning."""
    node, out = fusion
    _arrive(node, "/left/slip", _state(9.96, 0.99))
    _arrive(node, "/right/slip", _state(9.97, 0.98))
    _arrive(node, "/left/slip", _state(10.00, 0.05, grasp_s=10.0))  # /tracker/reset: left's new grasp
    assert out[-1].probability == pytest.approx(0.05) and not out[-1].slip  # not a mix with right's old grasp
    assert node.state == "ok" and node.counters["switching"] == 1 and node.counters["earlier_grasp"] == 0
    _arrive(node, "/right/slip", _state(10.01, 0.10, grasp_s=10.01))
    assert out[-1].probability == pytest.approx(camera_vote([0.05, 0.10])) and node.state == "ok"
    _arrive(node, "/left/slip", _state(20.00, 0.02, grasp_s=20.0))  # a reset that right missed
    _arrive(node, "/right/slip", _state(20.04, 0.90, grasp_s=10.01))
    assert out[-1].probability == pytest.approx(0.02) and node.state == "ok"
    _arrive(node, "/left/slip", _state(21.00, 0.03, grasp_s=20.0))
    _arrive(node, "/right/slip", _state(21.04, 0.90, grasp_s=10.01))
    assert out[-1].probability == pytest.approx(0.03)
    assert "/right/slip: on an earlier grasp" in node.message and node.counters["earlier_grasp"] == 1


def test_a_finger_that_never_answers_is_named_after_stale_after_s(fusion) -> None:
    node, out = fusion
    _arrive(node, "/left/slip", _state(1.0, 0.2))
    assert node.state == "ok"
    _arrive(node, "/left/slip", _state(2.1, 0.2))
    assert "/right/slip: no state yet" in node.message and node.state == "warn"


def test_a_stopped_camera_is_left_out_and_named(fusion) -> None:
    node, out = fusion
    _arrive(node, "/left/slip", _state(1.0, 0.2))
    _arrive(node, "/right/slip", _state(1.0, 0.9))
    _arrive(node, "/left/slip", _state(2.5, 0.3))
    assert out[-1].probability == pytest.approx(0.3)
    assert "/right/slip: no state for 1.5 s" in node.message and node.counters["stale"] == 1


def test_invalid_states_do_not_vote(fusion) -> None:
    node, out = fusion
    _arrive(node, "/left/slip", _state(1.0, 0.0, valid=False))
    assert not out[-1].valid and out[-1].probability == 0.0
    _arrive(node, "/right/slip", _state(1.01, 0.7))
    assert out[-1].valid and out[-1].probability == pytest.approx(0.7)


@pytest.mark.parametrize("params, message", [
    ({"inputs": ["/left/slip"]}, "two or more different topics"),
    ({"inputs": ["/a", "/a"]}, "two or more different topics"),
    ({"inputs": ["/slip", "/b"]}, "is also an input"),
    ({"stale_after_s": 0.0}, "must be > 0"),
    ({"inputs": ["left/slip", "/left/slip"]}, "two or more different topics"),  # one topic once resolved
    ({"inputs": ["/a", "slip"]}, "is also an input"),
    ({"inputs": ["/a", "b c"]}, "must start with '/'"),
    ({"threshold": 0.0}, "threshold 0.0 must be in"),
    ({"threshold": 1.5}, "threshold 1.5 must be in"),
])
def test_bad_params_are_refused(params: dict, message: str) -> None:
    from nodes.slip_fusion import SlipFusionParams
    with pytest.raises(ValueError, match=message):
        SlipFusionParams(**params)


def test_the_vote_decides_with_the_nodes_threshold_not_an_inputs(fusion) -> None:
    """An input state with threshold 0 (valid before SlipState refused it) made the vote slip at p=0."""
    node, out = fusion
    sneaky = _state(1.0, 0.0)
    sneaky.threshold = 0.0
    _arrive(node, "/left/slip", sneaky)
    assert not out[-1].slip and out[-1].threshold == 0.5
    high = SlipFusion("high", {"threshold": 0.8})
    try:
        high.setup()
        high.pub.publish = out.append
        _arrive(high, "/left/slip", _state(1.0, 0.7))
        assert not out[-1].slip and out[-1].threshold == 0.8
    finally:
        high.close()


def test_a_finger_whose_clock_is_behind_counts_while_its_states_arrive(fusion) -> None:
    """Right's clock 2 s behind left's: it was left out for good, "no state for 1.0 s", while its states came."""
    node, out = fusion
    for k in range(5):
        t = 10.0 + 0.033 * k
        _arrive(node, "/left/slip", _state(t, 0.05, grasp_s=9.9))
        _arrive(node, "/right/slip", _state(t - 2.0, 0.95, grasp_s=7.9), late_s=2.0)  # arrives at t; its grasp
        # began with left's, 7.9 s by its clock (it was left out as on an earlier grasp by the stamps alone)
        assert out[-1].probability == pytest.approx(camera_vote([0.05, 0.95])), k
        assert node.state == "ok", node.message


def test_a_state_stamped_far_ahead_is_refused_and_named(fusion) -> None:
    """One right state stamped 1 h ahead made left look stale; it is refused, named with its offset."""
    node, out = fusion
    _arrive(node, "/left/slip", _state(10.0, 0.1))
    _arrive(node, "/right/slip", _state(10.0, 0.1))
    _arrive(node, "/right/slip", _state(3610.0, 0.9), late_s=-3600.0)  # arrives at 10 s
    assert len(out) == 2 and node.counters["ahead"] == 1
    assert node.message.startswith("/right/slip: state refused, stamped 3600.0 s ahead of every input's clock and "
                                   "this host's"), node.message
    _arrive(node, "/left/slip", _state(10.05, 0.1))
    assert out[-1].probability == pytest.approx(0.1) and node.state == "ok" and node.counters["stale"] == 0


def test_inputs_are_told_apart_by_their_resolved_names() -> None:
    """In a namespace, `slip` and `/ns/slip` are one topic: refused at setup, before any vote."""
    node = SlipFusion("ns_fusion", {"inputs": ["slip", "/ns/slip"], "output": "/fused"}, namespace="ns")
    try:
        with pytest.raises(ValueError, match="two or more different topics"):
            node.setup()
    finally:
        node.close()
