"""Frame rates: the frames a camera at the model's rate would have filmed are kept, whatever the
jitter; a camera at the model's rate loses none; rates come from the table or the video, and a
camera too slow for the model is refused by name."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from fv_algos.frame_rate import FramePicker, check_rate, judged_rates, pick, picked_frames, trial_rate, video_rate
from fv_algos.real_trials import Trial, read_trials

MS = 1_000_000  # ns


def _kept(picker: FramePicker, stamps_ms) -> list[int]:
    return [i for i, t in enumerate(stamps_ms) if picker.accept(round(t * MS))]


def test_a_camera_at_the_model_rate_or_slower_loses_no_frame_to_jitter_stalls_or_bunching() -> None:
    rng = np.random.default_rng(0)
    jittered = np.arange(200) * 40.0 + rng.uniform(-8, 8, 200)
    assert _kept(FramePicker(25.0), np.sort(jittered)) == list(range(200))
    stalled = [0, 40, 80, 130, 130.2, 170, 210, 400, 401, 440]  # a stall, then two frames at once
    assert _kept(FramePicker(25.0), stalled) == list(range(len(stalled)))
    assert _kept(FramePicker(25.0), np.arange(50) * 66.7) == list(range(50))  # 15 fps: every frame, as it is
    assert _kept(FramePicker(25.0), np.arange(50) * 38.5) == list(range(50))  # 26 fps: within FASTER
    assert picked_frames(30, 25.0, 25.0).tolist() == list(range(30))


def test_a_faster_camera_keeps_the_frame_nearest_to_every_model_period() -> None:
    assert picked_frames(12, 50.0, 25.0).tolist() == [0, 2, 4, 6, 8, 10]
    fps, frames = 54.0, 400
    kept = picked_frames(frames, fps, 25.0)
    times = np.arange(frames) / fps
    nearest = np.unique([np.argmin(np.abs(times - k / 25.0)) for k in range(int(times[-1] * 25) + 1)])
    assert kept.tolist() == nearest.tolist()
    rng = np.random.default_rng(1)  # 50 fps with +/- 4 ms of jitter: still every other frame
    assert _kept(FramePicker(25.0), np.arange(100) * 20.0 + rng.uniform(-4, 4, 100)) == list(range(0, 100, 2))
    picker = FramePicker(25.0)
    _kept(picker, np.arange(7) * 20.0)
    picker.reset()  # a new grasp: its first frame is kept whatever its stamp
    assert picker.accept(140 * MS) and not picker.accept(160 * MS) and picker.accept(180 * MS)
    assert list(pick("abcdef", 50.0, 25.0)) == ["a", "c", "e"]
    with pytest.raises(ValueError, match="finite and > 0"):
        FramePicker(0.0)


def _trial(tmp_path: Path, fps_column: str | None, video: Path) -> Trial:
    extra = {} if fps_column is None else {"fps": fps_column}
    return Trial("t1", "cup", 1, tmp_path, {"camera_0": video}, extra)


def test_rates_come_from_the_table_or_the_video_and_bad_ones_are_named(tmp_path: Path) -> None:
    video = tmp_path / "camera_0.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 50.0, (64, 48))
    for k in range(3):
        writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
    writer.release()
    assert video_rate(video) == pytest.approx(50.0)
    assert trial_rate(_trial(tmp_path, None, video), "camera_0") == pytest.approx(50.0)
    assert trial_rate(_trial(tmp_path, " 30 ", video), "camera_0") == 30.0  # the table's column wins
    with pytest.raises(ValueError, match="trial t1: fps 'fast' is not a frame rate"):
        trial_rate(_trial(tmp_path, "fast", video), "camera_0")
    with pytest.raises(ValueError, match="trial t1: fps '-25'"):
        trial_rate(_trial(tmp_path, "-25", video), "camera_0")
    (tmp_path / "t1").mkdir()
    shutil.copy(video, tmp_path / "t1" / "camera_0.avi")
    (tmp_path / "labels.csv").write_text("trial,object,label,fps\nt1,cup,slip,25 fps\n")
    with pytest.raises(ValueError, match=r"labels.csv line 2: trial t1: fps '25 fps' is not"):  # the table's line
        trial_rate(read_trials(tmp_path)[0], "camera_0")
    (tmp_path / "notes.avi").write_text("not a video")
    with pytest.raises(ValueError, match="notes.avi: the video gives no frame rate"):
        video_rate(tmp_path / "notes.avi")


def test_judged_rates_take_the_most_common_rate_and_refuse_videos_too_slow_for_it(tmp_path: Path) -> None:
    video = tmp_path / "camera_0.avi"
    trials = [Trial(f"t{k}", "cup", 0, tmp_path, {"camera_0": video, "camera_2": video}, {"fps": str(fps)})
              for k, fps in enumerate((25, 25, 50))]
    assert judged_rates(trials) == (25.0, {("t2", "camera_0"): 50.0, ("t2", "camera_2"): 50.0})
    assert judged_rates(trials, fps=50.0, stretch=2.0) == (50.0, {})
    with pytest.raises(ValueError, match="trial t0 camera_0: 25 fps is slower than the model's 50 fps allows"):
        judged_rates(trials, fps=50.0, stretch=1.4)
    slow = [Trial(f"t{k}", "cup", 0, tmp_path, {"camera_0": video}, {"fps": str(fps)}) for k, fps in
            enumerate((60, 60, 25))]  # a training of mixed rates: its advice was the command that refused it
    with pytest.raises(ValueError, match=r"t2 camera_0: 25 fps is slower than the model's 60 fps allows .*: the "
                                         r"training takes the rate most of its videos have; --fps 25 trains at the"):
        judged_rates(slow, stretch=1.4)
    assert judged_rates(slow, fps=25.0, stretch=1.4)[0] == 25.0
    check_rate("v", 25.0 / 1.4, 25.0, 1.4, "")  # the slowest the training's stretch covers
    with pytest.raises(ValueError, match="v: 15 fps .* 17.9 fps at least\\): record faster"):
        check_rate("v", 15.0, 25.0, 1.4, "record faster")
