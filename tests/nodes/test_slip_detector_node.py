"""Slip-detector node: one SlipState per field once the window is full, stamps of the
judged fields, flagged (not NaN) output for a bad window, and a clear refusal of a
field grid the model was not trained for."""
from __future__ import annotations

import time

import numpy as np
import pytest

from msgs import DisplacementField
from nodes.bus import PublisherSocket, TopicReader
from nodes.slip_detector import model_path
from tests.nodes.conftest import wait_status


def _field(stamp_ns: int, value: float, grid: int = 30) -> DisplacementField:
    field = np.zeros((grid, grid, 3), np.float32)
    field[..., 0] = value
    field[..., 2] = abs(value)
    axis = np.linspace(0.0, 300.0, grid, dtype=np.float32)
    return DisplacementField(stamp_ns=stamp_ns, field=field, grid_x_px=axis, grid_y_px=axis)


def test_unknown_model_name_lists_the_shipped_ones() -> None:
    with pytest.raises(FileNotFoundError, match="gelsight"):
        model_path("no_such_model")


def test_decisions_per_field_with_window_stamps(bus, spawn) -> None:
    spawn("node", "slip_detector", "-p", "model=gelsight")
    wait_status("slip_detector", timeout_s=30.0)
    pub = PublisherSocket("test_fields")
    assert pub.wait_connected(5.0)
    with TopicReader(["/slip"]) as reader:
        deadline = time.monotonic() + 10.0
        while not pub.has_subscribers("/field") and time.monotonic() < deadline:
            time.sleep(0.05)
        stamps = [1_000_000_000 + i * 66_000_000 for i in range(14)]
        for i, stamp in enumerate(stamps):
            pub.publish("/field", _field(stamp, 0.3 * i))
            time.sleep(0.03)
        states = [reader.recv(10.0) for _ in range(5)]  # 14 fields, window 10: 5 decisions
        assert all(s is not None for s in states)
        for k, item in enumerate(states):
            s = item.msg
            assert 0.0 <= s.probability <= 1.0 and s.valid and s.model == "gelsight"
            assert list(s.window_stamps_ns) == stamps[k:k + 10] and s.stamp_ns == stamps[k + 9]
        # a non-finite field: the window is flagged invalid, the probability stays a number
        bad = _field(stamps[-1] + 66_000_000, 1.0)
        bad.field[3, 4, 0] = np.nan
        pub.publish("/field", bad)
        flagged = reader.recv(10.0).msg
        assert not flagged.valid and flagged.probability == 0.0
        # a grid the model was not trained for: counted as an error, the node keeps running
        pub.publish("/field", _field(stamps[-1] + 2 * 66_000_000, 1.0, grid=20))
        st = wait_status("slip_detector", lambda st: st.errors >= 1, 10.0)
        assert st.counters["invalid_windows"] >= 1
    pub.close()


def test_trial_level_model_is_refused_with_a_clear_error() -> None:
    from nodes.slip_detector import SlipDetectorNode
    node = SlipDetectorNode("slip_detector", {"model": "gelsight_trial"})
    try:
        with pytest.raises(ValueError, match="once per grasp"):
            node.setup()
    finally:
        node.close()
