"""slip_fusion: both fingers' vote after every state, never a mix of grasps, a stopped camera left
out and named, bad params refused; in stamp order, the same votes whichever finger's state arrives first."""
from __future__ import annotations

import time

import numpy as np
import pytest

from fv_algos.camera_vote import camera_vote
from msgs import SlipState
from nodes.bus import PublisherSocket, TopicReader
from nodes.slip_fusion import SlipFusion
from tests.nodes.conftest import spinning, wait_for, wait_status
from tests.nodes.fusion_votes import S, arrive, fused


def _state(stamp_s: float, p: float, grasp_s: float = 0.0, valid: bool = True) -> SlipState:
    return SlipState(stamp_ns=int(stamp_s * S), probability=p, slip=p >= 0.5, model="gelsight_online", valid=valid,
                     window_stamps_ns=np.array([int(grasp_s * S), int(stamp_s * S)], np.int64))


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
    arrive(node, "/left/slip", _state(0.04, 0.3))
    assert out[0].probability == pytest.approx(0.3) and node.state == "ok"  # right's first frame is due
    arrive(node, "/right/slip", _state(0.05, 0.9))
    assert out[1].probability == pytest.approx(camera_vote([0.3, 0.9])) and node.state == "ok"
    arrive(node, "/left/slip", _state(0.08, 0.8))
    assert out[2].probability == pytest.approx(camera_vote([0.8, 0.9])) and out[2].slip
    assert out[2].stamp_ns == int(0.08 * S) and list(out[2].window_stamps_ns) == [0, int(0.08 * S)]
    assert node.counters["voted"] == 3 and node.counters["alone"] == 1


def test_after_a_reset_a_finger_still_on_the_earlier_grasp_is_left_out(fusion) -> None:
    """Right's last state is from before left's new grasp: its reset frame is due, which is no fault. Still
    on the earlier grasp 1 s on (a camera that missed the reset), it is named in the warning."""
    node, out = fusion
    arrive(node, "/left/slip", _state(9.96, 0.99))
    arrive(node, "/right/slip", _state(9.97, 0.98))
    arrive(node, "/left/slip", _state(10.00, 0.05, grasp_s=10.0))  # /tracker/reset: left's new grasp
    assert out[-1].probability == pytest.approx(0.05) and not out[-1].slip  # not a mix with right's old grasp
    assert node.state == "ok" and node.counters["switching"] == 1 and node.counters["earlier_grasp"] == 0
    arrive(node, "/right/slip", _state(10.01, 0.10, grasp_s=10.01))
    assert out[-1].probability == pytest.approx(camera_vote([0.05, 0.10])) and node.state == "ok"
    arrive(node, "/left/slip", _state(20.00, 0.02, grasp_s=20.0))  # a reset that right missed
    arrive(node, "/right/slip", _state(20.04, 0.90, grasp_s=10.01))
    assert out[-1].probability == pytest.approx(0.02) and node.state == "ok"
    arrive(node, "/left/slip", _state(21.00, 0.03, grasp_s=20.0))
    arrive(node, "/right/slip", _state(21.04, 0.90, grasp_s=10.01))
    assert out[-1].probability == pytest.approx(0.03)
    assert "/right/slip: on an earlier grasp" in node.message and node.counters["earlier_grasp"] == 1


def test_a_finger_that_never_answers_is_named_after_stale_after_s(fusion) -> None:
    node, out = fusion
    arrive(node, "/left/slip", _state(1.0, 0.2))
    assert node.state == "ok"
    arrive(node, "/left/slip", _state(2.1, 0.2))
    assert "/right/slip: no state yet" in node.message and node.state == "warn"


def test_a_stopped_camera_is_left_out_and_named(fusion) -> None:
    node, out = fusion
    arrive(node, "/left/slip", _state(1.0, 0.2))
    arrive(node, "/right/slip", _state(1.0, 0.9))
    arrive(node, "/left/slip", _state(2.5, 0.3))
    assert out[-1].probability == pytest.approx(0.3)
    assert "/right/slip: no state for 1.5 s" in node.message and node.counters["stale"] == 1


def test_invalid_states_do_not_vote(fusion) -> None:
    node, out = fusion
    arrive(node, "/left/slip", _state(1.0, 0.0, valid=False))
    assert not out[-1].valid and out[-1].probability == 0.0
    arrive(node, "/right/slip", _state(1.01, 0.7))
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
    ({"order": "random"}, "order 'random' must be one of arrival, stamp"),
    ({"wait_s": 0.0}, "wait_s 0.0"),
    ({"wait_s": 0.01}, "wait_s 0.01 must be at least 0.05 s"),  # its timer, every 2 ms, starved the inputs
    ({"wait_s": float("inf")}, "wait_s inf must be at least 0.05 s and finite"),
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
    arrive(node, "/left/slip", sneaky)
    assert not out[-1].slip and out[-1].threshold == 0.5
    high = SlipFusion("high", {"threshold": 0.8})
    try:
        high.setup()
        high.pub.publish = out.append
        arrive(high, "/left/slip", _state(1.0, 0.7))
        assert not out[-1].slip and out[-1].threshold == 0.8
    finally:
        high.close()


def test_a_finger_whose_clock_is_behind_counts_while_its_statesarrive(fusion) -> None:
    """Right's clock 2 s behind left's: it was left out for good, "no state for 1.0 s", while its states came."""
    node, out = fusion
    for k in range(5):
        t = 10.0 + 0.033 * k
        arrive(node, "/left/slip", _state(t, 0.05, grasp_s=9.9))
        arrive(node, "/right/slip", _state(t - 2.0, 0.95, grasp_s=7.9), late_s=2.0)  # arrives at t; its grasp
        # began with left's, 7.9 s by its clock (it was left out as on an earlier grasp by the stamps alone)
        assert out[-1].probability == pytest.approx(camera_vote([0.05, 0.95])), k
        assert node.state == "ok", node.message


def test_a_state_stamped_far_ahead_is_refused_and_named(fusion) -> None:
    """One right state stamped 1 h ahead made left look stale; it is refused, named with its offset."""
    node, out = fusion
    arrive(node, "/left/slip", _state(10.0, 0.1))
    arrive(node, "/right/slip", _state(10.0, 0.1))
    arrive(node, "/right/slip", _state(3610.0, 0.9), late_s=-3600.0)  # arrives at 10 s
    assert len(out) == 2 and node.counters["ahead"] == 1
    assert node.message.startswith("/right/slip: state refused, stamped 3600.0 s ahead of every input's clock and "
                                   "this host's"), node.message
    arrive(node, "/left/slip", _state(10.05, 0.1))
    assert out[-1].probability == pytest.approx(0.1) and node.state == "ok" and node.counters["stale"] == 0


def test_inputs_are_told_apart_by_their_resolved_names() -> None:
    """In a namespace, `slip` and `/ns/slip` are one topic: refused at setup, before any vote."""
    node = SlipFusion("ns_fusion", {"inputs": ["slip", "/ns/slip"], "output": "/fused"}, namespace="ns")
    try:
        with pytest.raises(ValueError, match="two or more different topics"):
            node.setup()
    finally:
        node.close()


def _votes(params: dict, arrivals: list[tuple[str, SlipState, float]]) -> tuple[list[tuple[int, float]], dict]:
    """The (stamp, P(slip)) of each vote of :func:`fused`, and the fusion's counters."""
    out, counters = fused(params, arrivals)
    return [(s.stamp_ns, s.probability) for s in out], counters


def _two_fingers(left_late_s: float) -> list[tuple[str, SlipState, float]]:
    """20 frames of each finger at 25 Hz, right's stamped 10 ms after left's, in arrival order: left's states
    `left_late_s` after their stamps, right's at theirs (left's detector slower by more than 10 ms: right's first)."""
    rng = np.random.default_rng(3)
    states = [(t + late, topic, _state(t, float(p)), late) for k in range(20) for topic, t, late, p in
              [("/left/slip", 0.04 * k, left_late_s, rng.random()),
               ("/right/slip", 0.04 * k + 0.01, 0.0, rng.random())]]
    return [(topic, state, late) for _, topic, state, late in sorted(states, key=lambda s: s[0])]


def test_order_stamp_gives_the_same_votes_whichever_finger_arrives_first() -> None:
    """The two fingers' states arrive left first, or right first (left's detector slower): voted as they arrive
    the votes differ; in stamp order they are the same, every state voted with the other's latest before it."""
    early, late = _two_fingers(0.0), _two_fingers(0.025)
    assert [t for t, _, _ in early] != [t for t, _, _ in late]
    by_arrival = [_votes({}, arrivals)[0] for arrivals in (early, late)]
    assert by_arrival[0] != by_arrival[1]
    (first, counters), (second, _) = (_votes({"order": "stamp"}, arrivals) for arrivals in (early, late))
    assert first == second and len(first) == 40
    assert [stamp for stamp, _ in first] == sorted(stamp for _, state, _ in early for stamp in [state.stamp_ns])
    assert first == by_arrival[0]  # left's state of each frame arrived first, as stamped
    assert counters["waited"] == counters["late"] == counters["restarts"] == 0


def test_order_stamp_votes_a_state_after_wait_s_when_the_other_finger_is_silent() -> None:
    node = SlipFusion("slip_fusion", {"order": "stamp", "wait_s": 0.2})
    out: list[SlipState] = []
    try:
        node.setup()
        node.pub.publish = out.append
        arrive(node, "/left/slip", _state(1.00, 0.2))
        arrive(node, "/right/slip", _state(1.01, 0.9))
        arrive(node, "/left/slip", _state(1.04, 0.3))  # right's state of this frame is slow
        assert [s.probability for s in out] == pytest.approx([0.2, camera_vote([0.2, 0.9])])
        node.clock = lambda: 1.04 + 0.19
        node.on_timer()
        assert len(out) == 2
        node.clock = lambda: 1.04 + 0.21
        node.on_timer()
        assert out[-1].probability == pytest.approx(camera_vote([0.3, 0.9])) and node.counters["waited"] == 1
        arrive(node, "/right/slip", _state(1.03, 0.8), late_s=0.25)  # came after all: voted at once
        assert out[-1].probability == pytest.approx(camera_vote([0.3, 0.8])) and node.counters["late"] == 1
    finally:
        node.close()


def test_order_stamp_votes_states_of_one_stamp_together() -> None:
    """Both fingers' frames stamped alike (cameras triggered together): each state is voted with the other's of its
    stamp, not with the other's before it (the first input's was)."""
    arrivals = [("/left/slip", _state(1.00, 0.1), 0.0), ("/right/slip", _state(1.00, 0.9), 0.0),
                ("/left/slip", _state(1.04, 0.2), 0.0), ("/right/slip", _state(1.04, 0.3), 0.0)]
    votes, _ = _votes({"order": "stamp"}, arrivals)
    assert [stamp for stamp, _ in votes] == [int(1.00 * S)] * 2 + [int(1.04 * S)] * 2
    assert [p for _, p in votes] == pytest.approx([camera_vote([0.1, 0.9])] * 2 + [camera_vote([0.2, 0.3])] * 2)


def test_order_stamp_votes_what_is_held_when_the_node_stops(bus) -> None:
    """A left state held for right's is voted on the bus as the node stops."""
    node = SlipFusion("slip_fusion", {"order": "stamp", "wait_s": 30.0, "stale_after_s": 60.0})
    now = time.time()
    with TopicReader(["/slip"]) as reader:
        with spinning(node):
            wait_status("slip_fusion", timeout_s=5.0)
            pub = PublisherSocket("sender")
            try:
                assert pub.wait_connected(5.0)
                wait_for(lambda: pub.has_subscribers("/left/slip"), 5.0, "the fusion subscribing")
                pub.publish("/left/slip", _state(now, 0.3, grasp_s=now))
                wait_for(lambda: node.order.held() == 1, 5.0, "the state held")
                assert reader.recv(0.3) is None
            finally:
                pub.close()
        got = reader.recv(2.0)
    assert got is not None and got.msg.probability == pytest.approx(0.3) and got.msg.stamp_ns == int(now * S)
