"""Alarm rules and the online summary of running P(slip) series, on hand-made series."""
from __future__ import annotations

import numpy as np
import pytest

from fv_algos.grasp_alarm import AlarmRule, above_curves, online_summary


@pytest.mark.parametrize("rule, frame", [
    (AlarmRule(0.5), 2),  # the first frame at or above 0.5
    (AlarmRule(0.5, 0, 2), 5),  # frame 2 is alone; 4 and 5 are two in a row
    (AlarmRule(0.5, 3), 4),  # frame 2 comes before the first counted frame
    (AlarmRule(0.5, 5, 2), None),  # from frame 5 on, never two in a row
    (AlarmRule(0.9, 0, 1), 7),
    (AlarmRule(0.9, 0, 2), None),  # 0.95 at frame 7 is alone
    (AlarmRule(0.5, 0, 20), None),  # longer than the series
])
def test_first_alarm_counts_frames_in_a_row_from_the_first_counted_frame(rule: AlarmRule, frame: int | None) -> None:
    running = np.array([0.1, 0.4, 0.5, 0.2, 0.6, 0.7, 0.3, 0.95, 0.4])
    assert rule.first_alarm(running) == frame


def test_rules_parse_and_refuse_by_name() -> None:
    assert AlarmRule.parse("0.95:50:10") == AlarmRule(0.95, 50, 10)
    assert AlarmRule.parse("0.5") == AlarmRule(0.5, 0, 1) and AlarmRule.parse("0.7:3") == AlarmRule(0.7, 3, 1)
    assert str(AlarmRule(0.95, 50, 10)) == "P >= 0.95 from frame 50, 10 in a row"
    for bad in ("x", "0.5:y", "1.5", "0.5:1:0", "0.5:-2", "0.5:1:2:3", ""):
        with pytest.raises(ValueError, match=f"alarm rule {bad!r}"):
            AlarmRule.parse(bad)


def test_online_summary_counts_the_cameras_still_recording() -> None:
    held = [np.array([0.6, 0.2, 0.1, 0.1]), np.array([0.1, 0.1])]  # one grasp, two cameras
    slips = [[np.array([0.2, 0.7, 0.8, 0.9, 0.9])], [np.array([0.1, 0.1, 0.3])]]  # two grasps, one camera each
    labels = np.array([0, 1, 1])
    summary = online_summary([held, *slips], labels, fps=2.0, times_s=(0.0, 1.0, 2.0, 5.0),
                             rules=(AlarmRule(0.5), AlarmRule(0.5, 0, 3)))
    assert summary["cameras"] == {"held": 2, "slip": 2}
    assert summary["camera_end_accuracy"] == pytest.approx(3 / 4)  # only the second slip ends below 0.5
    assert summary["at"] == [
        {"seconds": 0.0, "frame": 0, "held_above": 0.5, "held_recording": 2, "slip_above": 0.0, "slip_recording": 2},
        {"seconds": 1.0, "frame": 2, "held_above": 0.0, "held_recording": 1, "slip_above": 0.5, "slip_recording": 2},
        {"seconds": 2.0, "frame": 4, "held_above": None, "held_recording": 0, "slip_above": 1.0, "slip_recording": 1},
        {"seconds": 5.0, "frame": 10, "held_above": None, "held_recording": 0, "slip_above": None,
         "slip_recording": 0}]
    first, in_row = summary["alarms"]
    assert (first["held_alarmed"], first["slip_alarmed"], first["slip_median_first_s"]) == (0.5, 0.5, 0.5)
    assert (in_row["held_alarmed"], in_row["slip_alarmed"], in_row["slip_median_first_s"]) == (0.0, 0.5, 1.5)
    held_curve, slip_curve = above_curves([held, *slips], labels)
    np.testing.assert_array_equal(held_curve, [0.5, 0.0, 0.0, 0.0, np.nan])
    np.testing.assert_array_equal(slip_curve, [0.0, 0.5, 0.5, 1.0, 1.0])


def test_online_summary_refuses_mismatched_input() -> None:
    with pytest.raises(ValueError, match="2 grasps' running P.slip. but 1 labels"):
        online_summary([[np.ones(3)], [np.ones(3)]], np.array([1]), fps=25.0)
    with pytest.raises(ValueError, match="no frame"):
        online_summary([[np.ones(0)]], np.array([1]), fps=25.0)
    with pytest.raises(ValueError, match="fps must be > 0"):
        online_summary([[np.ones(3)]], np.array([1]), fps=0.0)
