"""slip_monitor: the latency it prints runs from the frame's capture live, and from the frame's arrival in a
replay (whose capture stamps are the recorded session's) to the decision's."""
from __future__ import annotations

import time

import numpy as np
import pytest

from msgs import Image, SlipState
from nodes.slip_monitor import SlipMonitor, SlipMonitorParams

RECORDED_NS = 1_700_000_000_000_000_000  # a capture stamp from a session recorded long ago


def _monitor(params: dict) -> SlipMonitor:
    node = SlipMonitor("slip_monitor", params)
    node.setup()
    return node


def _latency_ms(line: str) -> float:
    return float(line.split("latency")[1].split("ms")[0])


@pytest.mark.parametrize("replay", [False, True])
def test_latency_is_from_the_capture_live_and_from_the_frame_s_arrival_in_a_replay(replay, capsys) -> None:
    node = _monitor({"frames": ["/camera/image"]} if replay else {})
    stamp = RECORDED_NS if replay else time.time_ns() - 20_000_000  # captured 20 ms ago
    if replay:
        node.on_frame(Image(stamp_ns=stamp, data=np.zeros((4, 4), np.uint8)))
    time.sleep(0.03)
    node.on_slip(SlipState(stamp_ns=stamp, probability=0.9, slip=True, pub_ns=time.time_ns()))
    line = capsys.readouterr().out
    assert "SLIP" in line and "p=0.90" in line
    assert (30 if replay else 50) <= _latency_ms(line) < 1000  # not the recorded session's age
    node.close()


def test_a_replayed_decision_read_after_its_frame_has_no_negative_latency(capsys) -> None:
    """The slip detector published its decision before this monitor read the frame (a busy monitor): the
    latency was the decision's publish time less the frame's arrival here, -0.8 ms."""
    node = _monitor({"frames": ["/camera/image"]})
    published_ns = time.time_ns()
    time.sleep(0.01)
    node.on_frame(Image(stamp_ns=RECORDED_NS, data=np.zeros((4, 4), np.uint8)))
    node.on_slip(SlipState(stamp_ns=RECORDED_NS, probability=0.9, slip=True, pub_ns=published_ns))
    assert 0.0 <= _latency_ms(capsys.readouterr().out) < 1000
    node.close()


def test_a_replayed_decision_whose_frame_was_not_seen_says_so(capsys) -> None:
    node = _monitor({"frames": ["/camera/image"]})
    node.on_slip(SlipState(stamp_ns=RECORDED_NS, probability=0.1, pub_ns=time.time_ns()))
    assert "latency  n/a (frame not seen)" in capsys.readouterr().out
    node.close()


def test_a_negative_period_is_refused() -> None:
    """every_s -1 was taken as 0 (changes only) without a word."""
    with pytest.raises(ValueError, match="every_s -1.0 must be >= 0"):
        SlipMonitorParams(every_s=-1.0)
