"""`fv param list | get | set` and `nodes.client.set_param`: a running node's params read from the node over
the bus; a live param (a slip detector's threshold) set without a restart, from its next decision on; every
refusal (a param taken only at start, a wrong type, an invalid value, an unknown param or node) named, with a
non-zero exit; a node named by its name or its ROS-style path; a malformed request dropped and counted by a
node that runs on."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from msgs import SlipState
from msgs.param import ParamSet, ParamState
from nodes.bus import PublisherSocket, TopicReader
from nodes.client import get_params, set_param
from nodes.param_service import param_topics
from nodes.params import ParamError
from nodes.registry import NODES, node_class
from nodes.slip_fusion import SlipFusion
from tests.nodes.conftest import poll_until, run_fv, spinning, wait_status
from tests.nodes.test_slip_detector_node import _field, _reference

FUSION = "left_slip_fusion"  # as `fv launch` names the node slip_fusion in the namespace `left`


@pytest.fixture
def fusion(bus):
    """A slip_fusion node in the namespace /left, spinning, its param state on the bus."""
    node = SlipFusion(FUSION, {"inputs": ["a/slip", "b/slip"], "output": "slip"}, namespace="/left")
    with spinning(node):
        get_params(FUSION, timeout_s=10.0)
        yield node


def test_get_reads_all_params_or_one_from_the_running_node(fusion) -> None:
    everything = run_fv("param", "get", FUSION, "--json")
    assert everything.returncode == 0, everything.stderr
    got = json.loads(everything.stdout)
    assert got["params"]["threshold"] == 0.5 and got["params"]["inputs"] == ["a/slip", "b/slip"]
    assert got["live"] == ["threshold"]
    one = run_fv("param", "get", FUSION, "threshold")
    assert one.returncode == 0 and one.stdout.strip() == "0.5"
    missing = run_fv("param", "get", FUSION, "nope")
    assert missing.returncode != 0 and f"node {FUSION!r} has no param 'nope'" in missing.stderr
    listed = run_fv("param", "list")  # every running node (discovered from /status) with its params
    assert listed.returncode == 0, listed.stderr
    assert f"{FUSION}:\n" in listed.stdout and "  threshold: 0.5  (live)" in listed.stdout
    assert "  same_grasp_s: 1.0\n" in listed.stdout


def test_set_applies_a_live_param_and_the_node_publishes_it(fusion) -> None:
    done = run_fv("param", "set", FUSION, "threshold", "0.8")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"{FUSION}: threshold set to 0.8"
    assert fusion.params.threshold == 0.8
    assert json.loads(run_fv("param", "get", FUSION, "threshold", "--json").stdout)["value"] == 0.8
    assert set_param(FUSION, "threshold", 0.3, timeout_s=10.0) == 0.3  # robot code: the same request
    with pytest.raises(ParamError, match="param 'inputs' takes effect only at start"):
        set_param(FUSION, "inputs", ["/x", "/y"], timeout_s=10.0)
    assert fusion.params.threshold == 0.3 and fusion.params.inputs == ["a/slip", "b/slip"]
    # a numpy scalar, as robot code computes it, is sent as its value (msgpack's TypeError before)
    assert set_param(FUSION, "threshold", np.float32(0.25), timeout_s=10.0) == 0.25 == fusion.params.threshold
    with pytest.raises(ParamError, match="param 'threshold': 1180591620717411303424 does not fit the 64-bit"):
        set_param(FUSION, "threshold", 2**70, timeout_s=10.0)  # (msgpack's bare OverflowError before)


@pytest.mark.parametrize("name, value, message", [
    ("stale_after_s", "2.0", "param 'stale_after_s' takes effect only at start: restart the node to change it "
                             "(set live: threshold)"),
    ("threshold", "abc", "param 'threshold' = 'abc' is not of type float"),
    ("threshold", "1.5", "threshold 1.5 must be in (0, 1)"),  # the params dataclass's own check
    ("nope", "1", "unknown param 'nope'"),
])
def test_a_refused_value_is_named_and_leaves_the_params_unchanged(fusion, name: str, value: str,
                                                                 message: str) -> None:
    refused = run_fv("param", "set", FUSION, name, value)
    assert refused.returncode != 0 and message in refused.stderr, refused.stderr
    assert f"node {FUSION!r}" in refused.stderr
    assert fusion.params.threshold == 0.5 and fusion.params.stale_after_s == 1.0


def test_a_node_is_also_named_by_its_ros_path(fusion) -> None:
    """/left/slip_fusion (or left/slip_fusion) is the node slip_fusion in the namespace left, the
    node `fv node list` shows as left_slip_fusion: for `fv param` and the client functions alike."""
    for path in ("/left/slip_fusion", "left/slip_fusion"):
        got = run_fv("param", "get", path, "threshold")
        assert got.returncode == 0 and got.stdout.strip() == "0.5", got.stderr
    done = run_fv("param", "set", "/left/slip_fusion", "threshold", "0.8")
    assert done.returncode == 0 and done.stdout.strip() == "/left/slip_fusion: threshold set to 0.8", done.stderr
    assert fusion.params.threshold == 0.8
    assert set_param("/left/slip_fusion", "threshold", 0.3, timeout_s=10.0) == 0.3
    assert get_params("left/slip_fusion", timeout_s=10.0)["threshold"] == fusion.params.threshold == 0.3


def test_a_launched_node_in_its_own_namespace_is_reached_by_its_path(bus, spawn, tmp_path) -> None:
    """Two launch entries `{name: fusion, namespace: left}` and `{..., namespace: right}` (refused before, both
    named fusion) are the nodes left_fusion and right_fusion, /left/fusion and /right/fusion to `fv param`."""
    launch = tmp_path / "pair.yaml"
    entry = "  - {{kind: slip_fusion, name: fusion, namespace: {}, params: {{inputs: [a, b], output: slip}}}}\n"
    launch.write_text("nodes:\n" + entry.format("left") + entry.format("right"))
    spawn("launch", str(launch))
    for path in ("/left/fusion", "right/fusion"):
        assert get_params(path, timeout_s=20.0)["threshold"] == 0.5
    done = run_fv("param", "set", "/right/fusion", "threshold", "0.7")
    assert done.returncode == 0 and done.stdout.strip() == "/right/fusion: threshold set to 0.7", done.stderr
    assert run_fv("param", "get", "right_fusion", "threshold").stdout.strip() == "0.7"
    assert run_fv("param", "get", "/left/fusion", "threshold").stdout.strip() == "0.5"


@pytest.mark.parametrize("verb", [("get",), ("set", "threshold", "0.7")])
@pytest.mark.parametrize("node, topic", [("slip_detector", "/slip_detector"), ("/slip_detector", "/slip_detector"),
                                         ("/right/slip_detector", "/right_slip_detector")])
def test_a_node_that_does_not_run_is_named_as_typed(bus, verb: tuple[str, ...], node: str, topic: str) -> None:
    result = run_fv("param", verb[0], node, *verb[1:], "--timeout", "0.5")
    assert result.returncode != 0
    assert f"no node {node!r} answers on {topic}/param/state within 0.5 s" in result.stderr


def test_a_path_without_a_name_is_refused(bus) -> None:
    result = run_fv("param", "get", "/")
    assert result.returncode == 2 and "'/' is not a node name or path" in result.stderr, result.stderr


def test_a_malformed_request_is_counted_and_the_node_runs_on(fusion) -> None:
    set_topic, state_topic = param_topics(FUSION)
    sock = PublisherSocket("test_bad_requests")
    try:
        assert sock.wait_connected(5.0)
        poll_until(lambda: sock.has_subscribers(set_topic), 10.0)
        sock.publish_raw(set_topic, "test_bad_requests", False, [b"\xc1 not msgpack"])
        sock.publish(set_topic, SlipState(stamp_ns=1))  # a message of another type
        with TopicReader([state_topic]) as reader:
            sock.publish(set_topic, ParamSet(request_id="r1", values={"threshold": {"a": 1}}))  # a value of no type
            answer = None
            while answer is None or answer.request_id != "r1":
                item = reader.recv(10.0)
                assert item is not None, "no answer to the request"
                answer = item.msg
            assert isinstance(answer, ParamState) and not answer.accepted and "is not of type float" in answer.error
    finally:
        sock.close()
    wait_status(FUSION, lambda st: st.malformed >= 2, timeout_s=10.0)
    assert set_param(FUSION, "threshold", 0.6, timeout_s=10.0) == 0.6  # it runs on


def test_a_new_threshold_decides_the_next_window_of_a_running_slip_detector(bus) -> None:
    """Fed windows of one probability p, a slip detector set live to a threshold on the other side of p
    flips its decision from the next window on, with its window kept (no restart, no window restart)."""
    from nodes.slip_detector import SlipDetectorNode

    node = SlipDetectorNode("slip_detector", {})
    pub = PublisherSocket("test_fields")
    stamps = iter(range(1_000_000_000, 10**12, 66_000_000))  # 15 fps

    def decision() -> SlipState:
        """The state of the next field (the window full)."""
        pub.publish("/field", _field(next(stamps), 0.5))
        item = reader.recv(10.0)
        assert item is not None, "no decision"
        return item.msg

    try:
        with spinning(node), TopicReader(["/slip"]) as reader:
            assert pub.wait_connected(5.0)
            wait_status("slip_detector", timeout_s=30.0)  # its model loaded
            poll_until(lambda: pub.has_subscribers("/field"), 10.0)
            pub.publish("/markers/reference", _reference(900_000_000, 640), latched=True)  # subscribed before /field
            for _ in range(node.classifier.config.window - 1):
                pub.publish("/field", _field(next(stamps), 0.5))
            before = decision()
            p = before.probability
            assert 0.0 < p < 1.0 and before.threshold == 0.5 and before.slip == (p > 0.5)
            threshold = (p + 1) / 2 if p > 0.5 else p / 2  # p on its other side
            assert set_param("slip_detector", "threshold", threshold, timeout_s=10.0) == threshold
            after = decision()
            assert after.threshold == threshold and after.probability == pytest.approx(p, abs=1e-6)
            assert after.slip != before.slip
            assert node.counters["window_restarts"] == 0 and node.params.threshold == threshold
    finally:
        pub.close()


@pytest.mark.parametrize("kind", sorted(NODES))
def test_every_live_param_is_a_param_of_its_node(kind: str) -> None:
    """A misspelt name in LIVE_PARAMS would list a live param the node has not, and leave the real one fixed."""
    cls = node_class(kind)
    assert cls.LIVE_PARAMS <= {f.name for f in dataclasses.fields(cls.Params)}
