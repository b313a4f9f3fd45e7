"""`fv eval --model M --trials DIR --json` on a user's folder of labelled recordings: the
whole real path from video to decision."""
from __future__ import annotations

import csv
import json
from pathlib import Path

from tests.conftest import write_raw_mini
from tests.nodes.conftest import run_fv


def test_eval_trials_on_two_real_trials(isd_data: Path, tmp_path: Path) -> None:
    rows = list(csv.DictReader(open(isd_data / "labels.csv")))
    picks = [next(r for r in rows if r["label"] == label) for label in ("slip", "no_slip")]
    with open(tmp_path / "labels.csv", "w") as f:  # the user's layout: DIR/<trial>/camera_0.avi
        f.write("trial,object,label\n")
        for i, r in enumerate(picks):
            (tmp_path / f"t{i}").symlink_to(isd_data / r["trial"])  # a link, the data stays in ../shared
            f.write(f"t{i},{r['object']},{r['label']}\n")
    result = run_fv("eval", "--trials", str(tmp_path), "--model", "gelsight", "--json", timeout_s=240)
    assert result.returncode == 0, result.stderr[-2000:]
    report = json.loads(result.stdout)
    assert report["n_trials"] == 2 and report["model"].endswith("slip_gelsight_trial.pt")
    assert 0.0 <= report["trial_accuracy"] <= 1.0
    assert report["window_accuracy"] is None  # the shipped gelsight decision is trial-level: no windows
    assert sum(map(sum, report["confusion"])) == 2
    assert [(t["trial"], t["label"]) for t in report["trials"]] == [("t0", "slip"), ("t1", "no_slip")]
    assert [t["correct"] for t in report["trials"]].count(True) == round(2 * report["trial_accuracy"])
    assert all(0.0 <= t["score"] <= 1.0 and t["slip"] == (t["score"] >= 0.5) for t in report["trials"])
    assert report["tracking"]["videos"] == 4 and report["tracking"]["valid_share_mean"] > 0.9


def test_eval_without_data_or_trials_is_a_clear_error() -> None:
    result = run_fv("eval", "--json", timeout_s=60)
    assert result.returncode == 2 and "--trials" in result.stderr and "Traceback" not in result.stderr


def test_raw_recordings_cut_as_read_are_judged_as_the_recorded_ones(isd_data: Path, tmp_path: Path) -> None:
    """`fv eval --trials RAW --crop 0.142857 --size 320 240` on a grasp's raw GelSight Mini frames (both
    cameras, :func:`write_raw_mini`) gives the recorded grasp's score: fields and contact motion alike."""
    trial = Path("train") / "marker_pen" / "exp_num_2"  # a slip, 53 frames per camera
    for folder in ("recorded", "raw"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "labels.csv").write_text("trial,object,label\nt0,marker_pen,slip\n")
    (tmp_path / "recorded" / "t0").symlink_to(isd_data / trial)
    (tmp_path / "raw" / "t0").mkdir()
    for camera in ("camera_0.avi", "camera_2.avi"):
        write_raw_mini(isd_data / trial / camera, tmp_path / "raw" / "t0" / camera)
    reports = {}
    for folder, cut in (("recorded", []), ("raw", ["--crop", "0.142857", "--size", "320", "240"])):
        result = run_fv("eval", "--trials", str(tmp_path / folder), "--model", "gelsight_online", "--json", *cut,
                        timeout_s=240)
        assert result.returncode == 0, result.stderr[-2000:]
        reports[folder] = json.loads(result.stdout)
    assert reports["raw"]["trials"][0]["score"] == reports["recorded"]["trials"][0]["score"]
    assert reports["raw"]["frames"] == reports["recorded"]["frames"] == 2 * 52


def test_a_bad_crop_is_refused_by_name_before_any_video_is_read(tmp_path: Path) -> None:
    result = run_fv("eval", "--trials", str(tmp_path / "absent"), "--model", "gelsight", "--crop", "0.1", "0.2",
                    timeout_s=60)
    assert result.returncode != 0 and "--crop / --size: crop [0.1, 0.2] must be" in result.stderr
