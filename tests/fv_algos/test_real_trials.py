"""Real labelled grasp trials: trial table, video fields and tracking quality, windows, trial
decisions, object-held-out folds and `fv eval-trials` (data tests skip without ../shared/data/isd)."""
from __future__ import annotations

import argparse
import json
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from fv_algos.atomic_file import write_atomically
from fv_algos.frame_crop import FrameCrop
from fv_algos.grasp_alarm import AlarmRule
from fv_algos.real_trials import (
    FIELD_WIDTH_PX,
    Trial,
    VideoFields,
    cache_path,
    load_video_fields,
    map_videos,
    read_cached,
    read_frames,
    read_trials,
    trial_fields,
    tracking_quality,
    video_fields,
)
from fv_algos.slip.classifier import Checkpoint, save_checkpoint
from fv_algos.slip.models import ModelConfig, build_model
from fv_algos.trial_eval import (
    TrialRule,
    balanced_rows,
    choose_threshold,
    cross_validate,
    fit_config,
    judge,
    object_folds,
    trial_scores,
    trial_windows,
    window_activity,
)
from fv_algos.trial_net import FIELD_ROWS, field_rows
from tests.conftest import write_raw_mini

SHORT_TRIALS = {  # trial -> (object, label): the shortest slip trials and the shortest no-slip trial
    "train/nylon_thread/exp_num_1": ("nylon_thread", "slip"),
    "train/marker_pen/exp_num_2": ("marker_pen", "slip"),
    "train/blue_mug/exp_num_5": ("blue_mug", "no_slip"),
}


def _subset(isd: Path, root: Path, trials: dict[str, tuple[str, str]] = SHORT_TRIALS) -> Path:
    """A trials folder in ``root`` with ``trials`` (trial -> (object, label); folders linked, not copied)."""
    lines = ["trial,object,label"]
    for name, (obj, label) in trials.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).symlink_to(isd / name, target_is_directory=True)
        lines.append(f"{name},{obj},{label}")
    (root / "labels.csv").write_text("\n".join(lines) + "\n")
    return root


def _write_mjpeg(path: Path, frames: Iterable[np.ndarray], fps: float = 25.0) -> None:
    """``frames`` (H, W, 3) BGR uint8, all of one size, as an MJPEG .avi at ``fps`` Hz (how the
    GelSight Mini trials are stored)."""
    frames = iter(frames)
    first = next(frames)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (first.shape[1], first.shape[0]))
    for frame in (first, *frames):
        writer.write(frame)
    writer.release()


def test_dataset_table_lists_150_trials_with_both_cameras(isd_data: Path) -> None:
    trials = read_trials(isd_data)
    assert len(trials) == 150
    assert sum(t.label for t in trials) == 65
    assert len({t.object for t in trials}) == 29
    assert all(set(t.videos) == {"camera_0", "camera_2"} for t in trials)
    assert all((t.folder / "slip.txt").is_file() == bool(t.label) for t in trials)
    assert "camera_0_frames" in trials[0].extra


def test_a_missing_table_is_named(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="labels.csv"):
        read_trials(tmp_path)


@pytest.mark.parametrize("table, error, message", [
    ("trial,object,label\nt1,cup,maybe\n", ValueError, r"labels.csv line 2: label 'maybe'"),
    ("trial,object,label\nt1,cup,slip\n", FileNotFoundError, r"t1/camera_0\{\.avi,\.mp4,\.mkv,\.mov,\.m4v\}"),
    ("trial,label\nt1,slip\n", ValueError, r"missing columns \['object'\]"),
    ("trial,object,label\nt1,cup\n", ValueError, r"labels.csv line 2: 2 fields, the header has 3"),
    ("trial,object,label\nt1, ,slip\n", ValueError, r"labels.csv line 2: trial 't1' has no object"),
    ("trial,object,label\n\nt1,cup,maybe\n", ValueError, r"labels.csv line 3: label 'maybe'"),  # after a blank line
    ("trial,object,label\nt1,cup,slip,extra\n", ValueError, r"labels.csv line 2: 4 fields, the header has 3"),
    ("trial,object,label,Label\nt1,cup,slip,slip\n", ValueError, r"labels.csv: a column is named twice"),
    ("trial,object,label\n,cup,slip\n", ValueError, r"labels.csv line 2: no trial"),
    # a quote never closed swallowed the lines after it: a later line was named, or a long table's cell too large
    pytest.param('trial,object,label\nt1,"cup,slip\nt2,mug,slip\nt3,mug,slip\n', ValueError,
                 r"labels.csv line 2: a quoted cell runs on to line 4 \(a quote never closed\?\)", id="open quote"),
    pytest.param('trial,object,label\nt1,"cup,slip\n' + "t2,mug,slip\n" * 12_000, ValueError,
                 r"labels.csv line 2: .*\(a quote never closed\?\)", id="open quote, long table"),
])
def test_bad_tables_name_the_file_and_line(tmp_path: Path, table: str, error: type, message: str) -> None:
    (tmp_path / "labels.csv").write_text(table)
    with pytest.raises(error, match=message):
        read_trials(tmp_path)


def test_a_spreadsheet_table_with_byte_order_mark_and_crlf_reads(tmp_path: Path) -> None:
    (tmp_path / "t1").mkdir()
    (tmp_path / "t1" / "camera_0.avi").write_bytes(b"")
    (tmp_path / "labels.csv").write_bytes("\ufefftrial,object,label\r\nt1,cup,slip\r\n".encode())
    [trial] = read_trials(tmp_path)
    assert (trial.name, trial.object, trial.label) == ("t1", "cup", 1)


def test_a_spreadsheet_table_reads_as_the_user_meant_it(tmp_path: Path) -> None:
    """Header cells with spaces or capitals, rows of empty cells below the table and trailing empty
    cells read; two names of one trial folder are refused, naming both lines."""
    for name in ("t1", "t2"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "camera_0.avi").write_bytes(b"")
    (tmp_path / "labels.csv").write_text("Trial, Object ,LABEL\nt1/,cup,slip,\n./t2,mug,No_Slip\n,,\n,,\n")
    assert [(t.name, t.object, t.label) for t in read_trials(tmp_path)] == [("t1", "cup", 1), ("t2", "mug", 0)]
    # columns without a name, a notes column among them (two or more were "a column is named twice")
    (tmp_path / "labels.csv").write_text("trial,object,label,,\r\nt1,cup,slip,,\r\nt2,mug,no_slip,,a note\r\n")
    assert [(t.name, t.label, t.extra) for t in read_trials(tmp_path)] == [("t1", 1, {}), ("t2", 0, {})]
    (tmp_path / "labels.csv").write_text("trial,object,label\nt1/,cup,slip\nt2,mug,no_slip\n./t1,cup,slip\n")
    with pytest.raises(ValueError, match=r"line 4: trial 't1' is listed twice \(also on line 2\)"):
        read_trials(tmp_path)
    (tmp_path / "labels.csv").write_bytes("trial,object,label\nt1,tasse \xe0 caf\xe9,slip\n".encode("latin-1"))
    with pytest.raises(ValueError, match=r"labels.csv line 2: not UTF-8 text .*byte 0xe0.*save it as UTF-8"):
        read_trials(tmp_path)


def test_a_second_camera_that_is_not_read_is_named(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A broken link where camera_2's video should be is refused; a video under another camera's
    name (camera_1.avi) is named in a warning: either used to leave the grasp to one camera unsaid."""
    (tmp_path / "t1").mkdir()
    (tmp_path / "t1" / "camera_0.avi").write_bytes(b"")
    (tmp_path / "t1" / "camera_1.avi").write_bytes(b"")
    (tmp_path / "labels.csv").write_text("trial,object,label\nt1,cup,slip\n")
    with caplog.at_level("WARNING"):
        [trial] = read_trials(tmp_path)
    assert set(trial.videos) == {"camera_0"}
    assert "labels.csv line 2: camera_1.avi left out: the cameras read are camera_0 and camera_2" in caplog.text
    (tmp_path / "t1" / "camera_2.avi").symlink_to(tmp_path / "gone.avi")
    with pytest.raises(ValueError, match=r"line 2: .*t1/camera_2.avi is not a video file \(a broken link"):
        read_trials(tmp_path)


def test_a_camera_video_may_be_any_common_container_but_only_one(tmp_path: Path) -> None:
    for name in ("t1/camera_0.mp4", "t1/camera_2.avi", "t2/camera_0.mkv"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "labels.csv").write_text("trial,object,label\nt1,cup,slip\nt2,mug,no_slip\n")
    assert [t.videos for t in read_trials(tmp_path)] == [
        {"camera_0": tmp_path / "t1/camera_0.mp4", "camera_2": tmp_path / "t1/camera_2.avi"},
        {"camera_0": tmp_path / "t2/camera_0.mkv"}]
    (tmp_path / "t2/camera_0.avi").write_bytes(b"")
    with pytest.raises(ValueError, match=r"labels.csv line 3: 2 videos for camera_0, keep one: .*t2/camera_0.avi, "):
        read_trials(tmp_path)
    (tmp_path / "t2/camera_0.avi").unlink()
    (tmp_path / "t2/camera_2.MP4").write_bytes(b"")  # was neither read nor warned of
    assert read_trials(tmp_path)[1].videos == {"camera_0": tmp_path / "t2/camera_0.mkv",
                                               "camera_2": tmp_path / "t2/camera_2.MP4"}
    (tmp_path / "t2/camera_0.mkv").rename(tmp_path / "t2/Camera_0.mkv")  # was "video not found", naming no file
    assert read_trials(tmp_path)[1].videos["camera_0"] == tmp_path / "t2/Camera_0.mkv"


def test_video_fields_track_every_frame_without_swaps(isd_data: Path) -> None:
    video = isd_data / "train/nylon_thread/exp_num_1/camera_0.avi"
    result = video_fields(video, reference_frame=1)
    assert result.fields.shape == (48, 30, 30, 3) and result.fields.dtype == np.float16
    assert np.all(result.fields[0] == 0) and result.field_valid.all()
    assert result.n_markers >= 30
    quality = result.quality()
    assert quality["valid_share_mean"] > 0.95 and quality["swaps"] == 0


def test_a_grasp_filmed_at_twice_the_resolution_gives_the_same_field_descriptors(isd_data: Path,
                                                                                   tmp_path: Path) -> None:
    """The field descriptors, and the window models' fields, are px of the frame at FIELD_WIDTH_PX wide:
    a 640x480 copy of a real slip gives the rows and windows of its 320x240 original within a tenth of
    their size (raw px would be twice them)."""
    video = isd_data / "train/marker_pen/exp_num_2/camera_0.avi"  # a slip, 53 frames
    large = tmp_path / "camera_0.avi"
    _write_mjpeg(large, (cv2.resize(f, (640, 480), interpolation=cv2.INTER_CUBIC) for f in read_frames(video)))
    original, copy = video_fields(video), video_fields(large)
    assert (original.width_px, copy.width_px) == (320, 640) == (FIELD_WIDTH_PX, 2 * FIELD_WIDTH_PX)
    rows = [field_rows(v.fields, v.valid_share, v.width_px) for v in (original, copy)]
    for column in (FIELD_ROWS.index(n) for n in ("field_px", "shear_x_px", "shear_y_px")):
        size = np.abs(rows[0][:, column]).mean()
        assert size > 1.0 and np.abs(rows[1][:, column] - rows[0][:, column]).mean() < 0.1 * size
    trial = Trial("t", "marker_pen", 1, tmp_path, {"camera_0": video})
    windows = [trial_windows([trial], {("t", "camera_0"): v}, 10, TrialRule()).windows for v in (original, copy)]
    assert all(w.sequences.frame_width_px == FIELD_WIDTH_PX for w in windows)
    fields = [w.sequences.fields.astype(np.float32)[..., 2] for w in windows]
    assert fields[0].mean() > 1.0 and np.abs(fields[1].mean() - fields[0].mean()) < 0.1 * fields[0].mean()


def test_map_videos_refuses_fewer_than_one_worker(tmp_path: Path) -> None:
    trial = Trial("t0", "o0", 0, tmp_path, {"camera_0": tmp_path / "camera_0.avi"})
    with pytest.raises(ValueError, match="workers must be >= 1, got 0"):
        map_videos([trial], str, workers=0)


def test_field_cache_round_trip(isd_data: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    trials = [t for t in read_trials(isd_data) if t.name == "train/nylon_thread/exp_num_1"]
    first = trial_fields(trials, tmp_path / "cache", progress=False)
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 2
    again = trial_fields(trials, tmp_path / "cache", progress=False)
    for key, value in first.items():
        np.testing.assert_array_equal(value.fields, again[key].fields)
    quality = tracking_quality(first)
    assert quality["videos"] == 2 and quality["frames"] == 96
    damaged = sorted((tmp_path / "cache").glob("*.npz"))[0]  # cut short on the disk: computed again, not fatal
    damaged.write_bytes(damaged.read_bytes()[:1000])          # (it ended in a BadZipFile naming no file)
    with caplog.at_level("WARNING"):
        healed = trial_fields(trials, tmp_path / "cache", progress=False)
    assert f"cache file {damaged} cannot be read" in caplog.text
    for key, value in first.items():
        np.testing.assert_array_equal(value.fields, healed[key].fields)
    assert read_cached(damaged, load_video_fields) is not None  # written whole again


def test_raw_frames_cut_as_read_give_the_recorded_fields_cached_apart(isd_data: Path, tmp_path: Path) -> None:
    """A GelSight Mini's raw frames (:func:`write_raw_mini`) read with the crop its software makes give the
    recorded video's fields, frame for frame; each crop has its own cache entry."""
    video = isd_data / "train" / "marker_pen" / "exp_num_2" / "camera_0.avi"
    raw = tmp_path / "camera_0.avi"
    write_raw_mini(video, raw)
    crop = FrameCrop.from_lists([0.142857], [320, 240])
    assert next(read_frames(raw, crop)).shape == (240, 320, 3)
    recorded, cut, uncut = video_fields(video), video_fields(raw, crop=crop), video_fields(raw)
    assert (cut.width_px, uncut.width_px) == (320, 448)
    np.testing.assert_array_equal(cut.fields, recorded.fields)
    np.testing.assert_array_equal(cut.valid_share, recorded.valid_share)
    other = FrameCrop.from_lists([0.1], [])
    assert len({cache_path(tmp_path, raw), cache_path(tmp_path, raw, 1, crop), cache_path(tmp_path, raw, 1, other)}) == 3


def test_a_truncated_video_is_named_with_the_frames_it_lost(isd_data: Path, tmp_path: Path,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    whole = isd_data / "train/nylon_thread/exp_num_1/camera_0.avi"  # 49 frames
    data = whole.read_bytes()
    (tmp_path / "t" / "cut").mkdir(parents=True)
    (tmp_path / "t" / "cut" / "camera_0.avi").write_bytes(data[:len(data) // 3])  # a copy broken off
    (tmp_path / "t" / "labels.csv").write_text("trial,object,label\ncut,o,slip\n")
    assert video_fields(whole).missing_frames == 0
    with caplog.at_level("WARNING", logger="fv_algos.real_trials"):
        fields = trial_fields(read_trials(tmp_path / "t"), tmp_path / "cache", progress=False)
    cut = fields[("cut", "camera_0")]
    assert 0 < cut.fields.shape[0] < 48 and cut.fields.shape[0] + 1 + cut.missing_frames == 49
    assert f"trial cut camera_0: the last {cut.missing_frames} frames its video lists could not be decoded" in caplog.text
    assert tracking_quality(fields)["short_videos"] == {"cut camera_0": cut.missing_frames}
    again = trial_fields(read_trials(tmp_path / "t"), tmp_path / "cache", progress=False)  # from the cache
    assert again[("cut", "camera_0")].missing_frames == cut.missing_frames
    assert cut.at(np.array([0])).missing_frames == cut.missing_frames


def test_a_cache_folder_that_cannot_be_one_is_named_before_any_video_is_decoded(tmp_path: Path) -> None:
    from fv_algos.contact_motion import trial_series
    (tmp_path / "t1").mkdir()
    (tmp_path / "t1" / "camera_0.avi").write_bytes(b"")  # never decoded: the cache is checked first
    (tmp_path / "labels.csv").write_text("trial,object,label\nt1,cup,slip\n")
    (tmp_path / "a_file").write_text("")
    for compute in (trial_fields, trial_series):
        with pytest.raises(ValueError, match=f"cache folder {tmp_path / 'a_file'} is a file"):
            compute(read_trials(tmp_path), tmp_path / "a_file", progress=False)
        with pytest.raises(ValueError, match=f"cache folder {tmp_path / 'a_file' / 'c'} cannot be created: "):
            compute(read_trials(tmp_path), tmp_path / "a_file" / "c", progress=False)


def test_cache_names_hash_all_the_code_their_results_come_from(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The field cache hashed the perception modules alone: fields written by another `float16_px`
    (real_trials.py) were read as current; the contact series hashed contact_motion.py alone."""
    import fv_algos.contact_motion as contact_motion
    import fv_algos.real_trials as real_trials
    from fv_algos.contact_motion import ContactMotionParams
    hashed: list[set[str]] = []

    def spy(*modules: object) -> str:
        hashed.append({Path(m.__file__).name for m in modules})
        return "0" * 64
    monkeypatch.setattr(real_trials, "code_digest", spy)
    monkeypatch.setattr(contact_motion, "code_digest", spy)
    video = tmp_path / "camera_0.avi"
    video.write_bytes(b"")
    real_trials.cache_path(tmp_path, video)
    contact_motion._series_cache_path(tmp_path, video, 1, ContactMotionParams(), None, None)
    assert {"real_trials.py", "reference_markers.py", "frame_crop.py", "detection.py", "tracking.py", "field.py",
            "perception.py"} <= hashed[0]
    assert {"contact_motion.py", "frame_rate.py", "frame_crop.py", "real_trials.py"} <= hashed[1]


def test_cache_files_are_written_whole_or_not_at_all(tmp_path: Path) -> None:
    target = tmp_path / "cache" / "a.npy"
    write_atomically(target, lambda tmp: np.save(tmp, np.arange(3)))
    np.testing.assert_array_equal(np.load(target), np.arange(3))

    def fail(tmp: Path) -> None:
        tmp.write_bytes(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_atomically(tmp_path / "cache" / "b.npy", fail)
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["a.npy"]  # no partial file, no temporary


def test_window_activity_of_uniform_motion() -> None:
    frames = np.zeros((20, 30, 30, 3), np.float16)
    frames[..., 0] = (0.5 * np.arange(20))[:, None, None]  # 0.5 px/frame in x
    np.testing.assert_allclose(window_activity(frames, 10, np.array([0, 5, 10])), 0.5, atol=1e-3)


def test_trial_scores_thresholds_balance_and_folds() -> None:
    probability = np.array([0.1, 0.9, 0.8, 0.2, 0.3, 0.1])
    trial = np.array([0, 0, 0, 1, 1, 1])
    np.testing.assert_allclose(trial_scores(probability, trial, 2, top_k=2), [0.85, 0.25])
    assert choose_threshold(np.array([0.1, 0.2, 0.8, 0.9]), np.array([0, 0, 1, 1])) == pytest.approx(0.5)
    rows = balanced_rows(np.arange(5), np.array([0, 0, 0, 0, 1]))
    assert np.count_nonzero(rows == 4) == 4 and rows.size == 8
    objects = ["a"] * 5 + ["b"] * 3 + ["c"] * 3 + ["d"] * 2 + ["e"]
    folds = object_folds(objects, 2)
    assert sorted(sum(folds, [])) == ["a", "b", "c", "d", "e"]
    counts = [sum(objects.count(o) for o in f) for f in folds]
    assert abs(counts[0] - counts[1]) <= 1


def test_windows_label_only_active_windows_of_slip_trials(isd_data: Path, tmp_path: Path) -> None:
    root = _subset(isd_data, tmp_path / "trials")
    trials = read_trials(root)
    data = trial_windows(trials, trial_fields(trials, tmp_path / "cache", progress=False), 10, TrialRule(stride=5))
    assert set(np.unique(data.trial)) == {0, 1, 2}
    assert data.labelled[data.labels == 0].all()
    slip = data.labels == 1
    np.testing.assert_array_equal(data.labelled[slip], data.activity[slip] >= TrialRule().activity_px)
    x, _ = data.windows.get(np.arange(4))
    assert x.shape == (4, 10, 30, 30, 3)


def test_eval_trials_command_from_video_to_decision(isd_data: Path, tmp_path: Path, capsys) -> None:
    from nodes.real_commands import eval_trials_command
    root = _subset(isd_data, tmp_path / "trials")
    torch.manual_seed(0)
    config = ModelConfig(arch="lstm", hidden=8)
    model_path = save_checkpoint(tmp_path / "tiny.pt", Checkpoint(config, build_model(config).state_dict()))
    args = argparse.Namespace(model=str(model_path), trials=root, cache=None, workers=1, json=True, online=False,
                              alarm=None, plot=None, crop=[], size=[], no_progress=True)
    assert eval_trials_command(args) == 0
    printed = capsys.readouterr()
    report = json.loads(printed.out)
    assert "frame" not in printed.err, printed.err  # --no-progress: no bar (there were two)
    assert report["n_trials"] == 3 and 0.0 <= report["trial_accuracy"] <= 1.0
    assert 0.0 <= report["window_accuracy"] <= 1.0
    assert np.sum(report["confusion"]) == 3
    assert report["tracking"]["videos"] == 6
    assert [t["trial"] for t in report["trials"]] == [t.name for t in read_trials(root)]
    assert sum(t["correct"] for t in report["trials"]) == round(3 * report["trial_accuracy"])


def test_fit_fine_tunes_from_a_checkpoint(isd_data: Path, tmp_path: Path) -> None:
    from fv_algos.trial_eval import fit
    root = _subset(isd_data, tmp_path / "trials")
    trials = read_trials(root)
    data = trial_windows(trials, trial_fields(trials, tmp_path / "cache", progress=False), 10, TrialRule(stride=5))
    config = ModelConfig(arch="lstm", hidden=8)
    start = save_checkpoint(tmp_path / "start.pt", Checkpoint(config, build_model(config).state_dict(), step=7))
    model, threshold, record = fit(data, np.arange(3), fit_config("convlstm", 16, steps=3, batch_size=4), init=str(start))
    assert model.config == config and record["steps"] == 10
    assert 0.0 <= threshold <= 1.0


def test_eval_trials_command_with_a_trial_level_model(isd_data: Path, tmp_path: Path, capsys) -> None:
    from fv_algos.trial_net import TrialNet, TrialNetConfig, save_trial_model
    from nodes.real_commands import eval_trials_command
    root = _subset(isd_data, tmp_path / "trials")
    net = TrialNet(4)
    with torch.no_grad():  # p = sigmoid(1) > 0.5: always slip
        for p in net.parameters():
            p.zero_()
        net.head.bias.fill_(1.0)
    path = save_trial_model(tmp_path / "trial.pt", net, TrialNetConfig(hidden=4, members=1))
    args = argparse.Namespace(model=str(path), trials=root, cache=tmp_path / "cache", workers=1, json=True,
                              online=False, alarm=None, plot=None, crop=[], size=[], no_progress=True)
    assert eval_trials_command(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["n_trials"] == 3 and report["window_accuracy"] is None
    assert report["confusion"] == [[0, 1], [0, 2]] and report["trial_accuracy"] == pytest.approx(2 / 3)
    assert len(list((tmp_path / "cache").glob("*__contact__*.npy"))) == 6
    still = [t.name for t in read_trials(root) if t.label == 0]
    assert [t["trial"] for t in report["trials"] if not t["correct"]] == still
    assert all(t["slip"] and t["score"] == pytest.approx(1 / (1 + np.exp(-1))) for t in report["trials"])
    assert eval_trials_command(argparse.Namespace(**{**vars(args), "json": False})) == 0
    wrong = [line for line in capsys.readouterr().out.splitlines() if line.startswith("  wrong: ")]
    assert wrong == [f"  wrong: {still[0]} (blue_mug): no_slip, score 0.73"]
    online = {**vars(args), "online": True, "alarm": [AlarmRule(0.5, 30, 5)]}
    assert eval_trials_command(argparse.Namespace(**online)) == 0  # the constant net: every camera above 0.5
    report = json.loads(capsys.readouterr().out)["online"]
    assert report["cameras"] == {"held": 2, "slip": 4} and report["camera_end_accuracy"] == pytest.approx(4 / 6)
    assert report["at"][0] == {"seconds": 0.4, "frame": 10, "held_above": 1.0, "held_recording": 2,
                               "slip_above": 1.0, "slip_recording": 4}
    assert report["alarms"] == [{"rule": "P >= 0.5 from frame 30, 5 in a row", "threshold": 0.5, "from_frame": 30,
                                 "in_row": 5, "held_alarmed": 1.0, "slip_alarmed": 1.0,
                                 "slip_median_first_s": 34 / 25}]


def test_real_train_writes_a_trial_model_that_fv_eval_reads(isd_data: Path, tmp_path: Path, capsys) -> None:
    from nodes.cli import main
    root = _subset(isd_data, tmp_path / "trials")
    out = tmp_path / "slip_mine_trial.pt"
    assert main(["real", "train", "--trials", str(root), "--cache", str(tmp_path / "cache"), "--steps", "5",
                 "--hidden", "4", "--members", "2", "--reference-frame", "5", "--out", str(out)]) == 0
    info = json.loads(out.with_suffix(".json").read_text())
    assert info["trained_on"]["trials"] == 3 and info["config"]["steps"] == 5 and info["config"]["members"] == 2
    assert info["parameters"] == 2 * 485  # per member: 224 + 3 * 84 in the convolutions, 9 in the head
    assert info["config"]["reference_frame"] == 5
    assert info["config"]["balance"] == "setup" and list(info["setups"].values()) == [{"slip": 2, "no_slip": 1}]
    cached = sorted((tmp_path / "cache").glob("*.np[yz]"))
    assert len(cached) == 12  # fields and contact series of 6 videos, from frame 5 on
    capsys.readouterr()
    assert main(["eval", "--trials", str(root), "--model", str(out), "--cache", str(tmp_path / "cache"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["n_trials"] == 3 and report["method"].startswith("trial") and report["window_accuracy"] is None
    assert sorted((tmp_path / "cache").glob("*.np[yz]")) == cached  # fv eval judged the model's frames
    tuned = tmp_path / "slip_tuned_trial.pt"  # fine-tuned from it: its shape, not --hidden's default 16
    assert main(["real", "train", "--trials", str(root), "--cache", str(tmp_path / "cache"), "--steps", "3",
                 "--reference-frame", "5", "--init", str(out), "--balance", "label", "--out", str(tuned)]) == 0
    info = json.loads(tuned.with_suffix(".json").read_text())
    assert info["config"]["balance"] == "label" and info["setups"] is None
    assert info["init"] == str(out) and info["parameters"] == 2 * 485
    assert (info["config"]["hidden"], info["config"]["members"], info["config"]["steps"]) == (4, 2, 3)
    windows = tmp_path / "slip_tuned_windows.pt"  # a window model fine-tuned: saved with its architecture
    assert main(["real", "train", "--trials", str(root), "--cache", str(tmp_path / "cache"), "--method", "windows",
                 "--steps", "2", "--init", "sim_cnn_lstm", "--out", str(windows)]) == 0
    from fv_algos.slip.classifier import load_checkpoint
    from nodes.shipped_models import model_path
    assert load_checkpoint(windows).model_config == load_checkpoint(model_path("sim_cnn_lstm")).model_config
    assert json.loads(windows.with_suffix(".json").read_text())["fit"]["init"] == str(model_path("sim_cnn_lstm"))


def test_real_cv_online_reports_how_early_the_held_out_networks_tell_slips(isd_data: Path, tmp_path: Path,
                                                                           capsys, caplog) -> None:
    from nodes.cli import main
    # two groups, each with a slip and a held grasp, so that every training fold has both
    trials = {**{name: ("a" if name.startswith("train/nylon") or name.startswith("train/blue") else "b", label)
                 for name, (_, label) in SHORT_TRIALS.items()},
              "train/cheese_tube/exp_num_3": ("b", "no_slip")}
    root = _subset(isd_data, tmp_path / "trials", trials)
    out, plot = tmp_path / "cv.json", tmp_path / "online.png"
    argv = ["real", "cv", "--trials", str(root), "--cache", str(tmp_path / "cache"), "--folds", "2", "--steps", "5",
            "--hidden", "4", "--members", "1", "--online", "--alarm", "0.5:25:5"]
    assert main([*argv, "--plot", str(plot), "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    online = report["online"]
    assert "running" not in report and online["cameras"] == {"held": 4, "slip": 4} and online["fps"] == 25.0
    assert list(report["setups"].values()) == [{"slip": 2, "no_slip": 2}]  # one magnification: one set-up
    assert [row["frame"] for row in online["at"]] == [10, 25, 50, 100, 200, 300]
    assert [row["rule"] for row in online["alarms"]] == ["P >= 0.5 from frame 25, 5 in a row"]
    assert plot.stat().st_size > 0 and online["plot"] == str(plot)
    running = json.loads(out.read_text())["running"]  # per trial, per camera: P(slip) after every frame
    read = read_trials(root)
    fields = trial_fields(read, tmp_path / "cache")
    assert [[len(c) for c in cameras] for cameras in running] == [
        [fields[(t.name, c)].fields.shape[0] for c in ("camera_0", "camera_2")] for t in read]
    def logit(p: float) -> float:
        return float(np.log(p / (1.0 - p)))
    for fold in report["folds"]:  # the head is linear in the pooled features, which average the cameras:
        for i, p in zip(fold["trials"], fold["probability"]):  # the trial's logit is its cameras' last ones' mean
            assert logit(p) == pytest.approx(np.mean([logit(c[-1]) for c in running[i]]), abs=1e-4)
    assert main([*argv]) == 0  # the text report names every check time and rule (the plot is drawn above)
    text = capsys.readouterr().out
    assert "at 0.4 s: P >= 0.5 for" in text and "alarm P >= 0.5 from frame 25, 5 in a row:" in text
    model = tmp_path / "mine_trial.pt"  # a model trained beside this report records its online part
    assert main(["real", "train", "--trials", str(root), "--cache", str(tmp_path / "cache"), "--steps", "5",
                 "--hidden", "4", "--members", "1", "--out", str(model), "--cv-report", str(out)]) == 0
    sidecar = json.loads(model.with_suffix(".json").read_text())
    assert sidecar["cross_validation_online"] == {k: v for k, v in online.items() if k != "plot"}
    other = tmp_path / "other_trial.pt"  # trained on other trials than the report's: refused before any video is read
    fewer = _subset(isd_data, tmp_path / "fewer", dict(list(trials.items())[:-1]))  # (its figures were recorded)
    assert main(["real", "train", "--trials", str(fewer), "--steps", "5", "--hidden", "4", "--members", "1",
                 "--out", str(other), "--cv-report", str(out)]) == 2
    assert (f"the report cross-validated other trials: {len(trials)} trials of 2 objects (this training: "
            f"{len(trials) - 1} of 2)") in capsys.readouterr().err and not other.exists()
    assert main(["real", "train", "--trials", str(tmp_path / "absent"), "--steps", "6",  # trained otherwise
                 "--hidden", "4", "--members", "1", "--balance", "label", "--out", str(other),
                 "--cv-report", str(out)]) == 2
    err = capsys.readouterr().err
    assert ("the report's networks were trained otherwise: steps 5 (this training: 6); balance 'setup' (this "
            "training: 'label')") in err and not other.exists()
    assert main(["real", "train", "--trials", str(root), "--method", "windows", "--out", str(other),
                 "--cv-report", str(out)]) == 2
    assert "the report cross-validated the trial model, this trains the windows one" in capsys.readouterr().err
    assert not other.exists()
    window_argv = ["--trials", str(root), "--cache", str(tmp_path / "cache"), "--method", "windows"]
    report = tmp_path / "windows_cv.json"  # a window model's report is checked against its training too
    assert main(["real", "cv", *window_argv, "--steps", "2", "--folds", "2", "--out", str(report)]) == 0
    capsys.readouterr()
    assert main(["real", "train", *window_argv, "--steps", "3", "--out", str(other), "--cv-report", str(report)]) == 2
    assert "trained otherwise: train.steps 2 (this training: 3)" in capsys.readouterr().err and not other.exists()
    assert main(["real", "train", *window_argv, "--steps", "2", "--out", str(other), "--cv-report", str(report)]) == 0
    assert json.loads(other.with_suffix(".json").read_text())["cross_validation"] == json.loads(
        report.read_text())["summary"]
    alone = tmp_path / "alone" / other.name  # copied without its .json: judged with threshold 0.5, said so
    alone.parent.mkdir()
    alone.write_bytes(other.read_bytes())
    with caplog.at_level("WARNING"):
        assert main(["eval", "--trials", str(root), "--cache", str(tmp_path / "cache"), "--model", str(alone)]) == 0
    assert f"no {other.with_suffix('.json').name} beside {alone}: judged with trial threshold 0.5" in caplog.text


@pytest.mark.parametrize("argv, message", [
    (["real", "cv", "--trials", "x", "--plot", "x.png"], "fv real: error: --plot needs --online"),  # exit 1
    (["real", "cv", "--trials", "x", "--online", "--method", "windows"], "--online needs a trial-level model"),
    (["real", "cv", "--trials", "x", "--init", "sim"], "is not a trial-level slip model"),  # a window model
    (["real", "cv", "--trials", "x", "--balance", "labels"], "balance one of setup, label (got 'labels')"),
    (["eval", "--trials", "x", "--model", "sim", "--online"], "--online needs a trial-level model"),
    (["eval", "--trials", "x", "--model", "gelsight_trial", "--alarm", "0.9", "--plot", "x.png"],
     "fv eval: error: --alarm and --plot need --online"),
])
def test_bad_flags_are_refused_by_name(argv: list[str], message: str, capsys) -> None:
    from nodes.cli import main
    assert main(argv) == 2 and message in capsys.readouterr().err


def test_what_the_table_alone_refuses_is_refused_before_any_video_is_read(tmp_path: Path, capsys) -> None:
    """A deal of more folds than objects, and a training set of mixed rates whose slower videos its rate (the
    most common) cannot take, were refused once every video's fields were computed (here the videos are empty
    files: reading one is an error of its own); the rates' advice named the command that refused them."""
    from nodes.cli import main
    for k in range(3):
        (tmp_path / f"t{k}").mkdir()
        (tmp_path / f"t{k}" / "camera_0.avi").write_bytes(b"")
    (tmp_path / "labels.csv").write_text("trial,object,label,fps\nt0,cup,slip,60\nt1,mug,no_slip,60\nt2,mug,slip,25\n")
    cache = tmp_path / "cache"
    assert main(["real", "cv", "--trials", str(tmp_path), "--cache", str(cache), "--folds", "3"]) == 2
    assert "folds must be in [2, 2] (the number of objects), got 3" in capsys.readouterr().err
    assert main(["real", "train", "--trials", str(tmp_path), "--cache", str(cache), "--out",
                 str(tmp_path / "m.pt")]) == 2
    assert ("trial t2 camera_0: 25 fps is slower than the model's 60 fps allows (its training stretched time by up "
            "to 1.4x, so 42.9 fps at least): the training takes the rate most of its videos have; --fps 25 trains at "
            "the slowest") in capsys.readouterr().err
    assert not cache.exists()


@pytest.mark.parametrize("rule", ["0.5:x", "1.5", "0.5:1:2:3", "0.5:-1"])
def test_real_cv_refuses_a_bad_alarm_rule_by_name(rule: str, capsys) -> None:
    from nodes.cli import main
    with pytest.raises(SystemExit) as exit_info:
        main(["real", "cv", "--trials", "x", "--online", "--alarm", rule])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "argument --alarm" in err and f"alarm rule {rule!r}" in err


def test_a_set_whose_rule_labels_no_window_is_judged_at_trial_level(tmp_path: Path) -> None:
    """A still grasp labelled slip: the rule labels none of its windows (no motion to call slip). Its
    window accuracy is None (it ended `fv eval --trials` and `fv real cv --method windows` in "labels and
    predicted must be equal-length non-empty 1-D arrays"); the trial is still judged."""
    trial = Trial("t0", "o0", 1, tmp_path, {"camera_0": tmp_path / "camera_0.avi"})
    fields = {("t0", "camera_0"): VideoFields(np.zeros((20, 30, 30, 3), np.float16), np.ones(20, bool),
                                              np.ones(20, np.float32), np.zeros(20, np.int32), 40, 0.1, 320)}
    data = trial_windows([trial], fields, 10, TrialRule(stride=5))
    assert not data.labelled.any()
    report = judge(build_model(ModelConfig(arch="lstm", hidden=8)).eval(), data, np.arange(1), 0.5, 3)
    assert report["window_accuracy"] is None and report["n_windows"] == 0
    assert report["n_trials"] == 1 and sum(map(sum, report["confusion"])) == 1


def test_window_cross_validation_gives_the_same_folds_in_two_processes(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    trials, fields = [], {}
    for i in range(6):  # three objects, one slip (growing shear) and one still trial each
        trial = Trial(f"t{i}", f"o{i // 2}", i % 2, tmp_path, {"camera_0": tmp_path / "camera_0.avi"})
        motion = np.linspace(0.0, 12.0 * trial.label, 20)[:, None, None, None] * np.ones((20, 30, 30, 3))
        video = (motion + rng.normal(0.0, 0.05, motion.shape)).astype(np.float16)
        fields[(trial.name, "camera_0")] = VideoFields(video, np.ones(20, bool), np.ones(20, np.float32),
                                                       np.zeros(20, np.int32), 40, 0.1, 320)
        trials.append(trial)
    data = trial_windows(trials, fields, 10, TrialRule(stride=5))
    config = fit_config("lstm", 8, steps=3, batch_size=8)
    one = cross_validate(data, config, folds=3, progress=False)
    two = cross_validate(data, config, folds=3, progress=False, workers=2)
    for report in (one, two):  # training time is measured, so it differs; everything else must not
        for fold in report["folds"]:
            fold["training"].pop("windows_per_s")
            fold["training"]["monitor"].pop("elapsed_s")
    assert two == one and sorted(f["objects"] for f in one["folds"]) == [["o0"], ["o1"], ["o2"]]
    with pytest.raises(ValueError, match="workers must be >= 1"):
        cross_validate(data, config, folds=3, progress=False, workers=0)


def test_fv_eval_judges_a_faster_camera_on_the_frames_of_the_model_rate(isd_data: Path, tmp_path: Path,
                                                                         capsys) -> None:
    """The same grasp filmed at 25 fps, and at 50 fps (every frame after the reference twice): `fv eval`
    picks the 50 fps video's frames at the model's 25 fps and judges it as the 25 fps one; judged at its
    own rate (the table says 25 fps) it sees every motion at half the speed. A rate the model cannot take
    is refused by name."""
    from nodes.cli import main
    frames = list(read_frames(isd_data / "train" / "ball_white_thread" / "exp_num_5" / "camera_0.avi"))  # a slip
    for name, fps, video in (("at25", 25.0, frames), ("at50", 50.0, [frames[0]] + [f for f in frames[1:] for _ in "ab"])):
        (tmp_path / name).mkdir()
        _write_mjpeg(tmp_path / name / "camera_0.avi", video, fps)

    def scores(table: str, frames_judged: int) -> list[float]:
        (tmp_path / "labels.csv").write_text(table)
        assert main(["eval", "--trials", str(tmp_path), "--model", "gelsight_trial", "--json"]) == 0
        report = json.loads(capsys.readouterr().out)
        assert report["model_fps"] == 25.0 and report["frames_judged"] == frames_judged
        assert report["frames"] == 3 * (len(frames) - 1)  # tracked: every frame from the reference on
        return [t["score"] for t in report["trials"]]
    at25, at50 = scores("trial,object,label\nat25,ball,slip\nat50,ball,slip\n", 2 * (len(frames) - 1))
    assert at25 > 0.5 and at50 == pytest.approx(at25, abs=0.01)
    _, unpicked = scores("trial,object,label,fps\nat25,ball,slip,25\nat50,ball,slip,25\n", 3 * (len(frames) - 1))
    assert unpicked < 0.5  # this slip, seen at half its speed, is called held
    (tmp_path / "labels.csv").write_text("trial,object,label,fps\nat25,ball,slip,12\n")
    assert main(["eval", "--trials", str(tmp_path), "--model", "gelsight_trial", "--json"]) == 2
    assert "trial at25 camera_0: 12 fps is slower than the model's 25 fps allows" in capsys.readouterr().err


@pytest.mark.parametrize("model", ["gelsight_trial", "sim_fast"])
def test_fv_eval_refuses_a_video_too_short_to_judge_by_name(isd_data: Path, tmp_path: Path, model: str,
                                                            capsys) -> None:
    """A grasp of fewer than 10 frames from the reference on is refused, trial and camera named, by a trial
    model and a window model alike (it was judged from a frame or two, or scored NaN and called held)."""
    from nodes.cli import main
    frames = list(read_frames(isd_data / "train" / "nylon_thread" / "exp_num_1" / "camera_0.avi"))
    (tmp_path / "short").mkdir()
    _write_mjpeg(tmp_path / "short" / "camera_0.avi", frames[:6])  # the stale frame 0, the reference and 4 more
    _subset(isd_data, tmp_path, {"train/blue_mug/exp_num_5": ("blue_mug", "no_slip")})
    with (tmp_path / "labels.csv").open("a") as table:
        table.write("short,nylon_thread,slip\n")
    assert main(["eval", "--trials", str(tmp_path), "--model", model, "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert ("1 video(s) too short to judge, fewer than 10 frames judged from the reference on (frames in brackets): "
            "short camera_0 (5)") in captured.err
