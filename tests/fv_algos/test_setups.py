"""Set-ups: trials told apart by their table's setup column, else by the markers' pitch in their reference frame."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from fv_algos.real_trials import Trial, read_trials
from fv_algos.setups import marker_pitch, pitch_setups, setup_counts, trial_setups

LONG, SHORT = "train/artificial_strawberry/exp_num_1", "train/nylon_thread/exp_num_1"  # 450 and 58 frames


def test_pitches_far_apart_are_set_ups_of_their_own() -> None:
    assert pitch_setups([31.0, 44.2, 30.2, 42.9, 31.9]) == ["pitch 30-32 px", "pitch 43-44 px", "pitch 30-32 px",
                                                            "pitch 43-44 px", "pitch 30-32 px"]
    assert pitch_setups([30.0, 35.0, 41.0, 48.0]) == ["pitch 30-48 px"] * 4  # no step above 1.2: one set-up
    assert pitch_setups([30.0, 35.0, 41.0, 48.0], step=1.1) == ["pitch 30-30 px", "pitch 35-35 px",
                                                                 "pitch 41-41 px", "pitch 48-48 px"]
    assert pitch_setups([]) == []
    with pytest.raises(ValueError, match=r"marker pitches must be finite and > 0, got \[nan  0.\]"):
        pitch_setups([30.0, float("nan"), 45.0, 0.0])  # a NaN took 45 px into a set-up "pitch nan-nan px"


def test_setup_counts_per_label() -> None:
    counts = setup_counts(["b", "a", "b", "b"], np.array([1, 0, 0, 1]))
    assert counts == {"a": {"slip": 0, "no_slip": 1}, "b": {"slip": 2, "no_slip": 1}}


def _trial(name: str, folder: Path, extra: dict[str, str], row: str = "") -> Trial:
    return Trial(name, "object", 1, folder, {"camera_0": folder / "camera_0.avi"}, extra, row)


def test_the_tables_setup_column_names_the_set_ups_else_the_marker_pitch(isd_data: Path) -> None:
    """The 150 grasps' two magnifications: a 450-frame grasp at 30-32 px, a short one at 43-44 px."""
    trials = {t.name: t for t in read_trials(isd_data)}
    pair = [trials[LONG], trials[SHORT]]
    assert trial_setups(pair) == ["pitch 32-32 px", "pitch 43-43 px"]
    named = [_trial(t.name, t.folder, {"setup": s}) for t, s in zip(pair, ["rig A", " rig B "])]
    assert trial_setups(named) == ["rig A", "rig B"]
    half = [_trial(t.name, t.folder, {"setup": s}, row) for t, s, row in zip(pair, ["rig A", ""], ["", "x line 3"])]
    with pytest.raises(ValueError, match=rf"the setup column names the set-up of 1 trials but not of 1: {SHORT} "
                                         r"\(x line 3\)"):
        trial_setups(half)  # a cell left empty: the pitch was taken for every trial, without a word


def test_a_video_without_markers_or_frames_is_named(tmp_path: Path) -> None:
    blank = tmp_path / "blank.avi"
    writer = cv2.VideoWriter(str(blank), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48))
    for _ in range(3):
        writer.write(np.full((48, 64, 3), 128, np.uint8))
    writer.release()
    with pytest.raises(ValueError, match=f"video {blank}, frame 1: "):
        marker_pitch(blank, 1)
    empty = tmp_path / "empty.avi"
    cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48)).release()
    with pytest.raises(ValueError, match="no frame to measure the marker pitch in"):
        marker_pitch(empty, 1)
