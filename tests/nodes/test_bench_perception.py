"""`fv bench perception` on a very short setting: JSON keys, sanity of numbers, report files."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from nodes import bench_perception
from nodes.cli import build_parser


def _run(argv: list[str]) -> int:
    args = build_parser().parse_args(["bench", *argv])
    return args.func(args)


def test_quick_benchmark_json_and_report(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = _run(["perception", "--quick", "--frames", "3", "--config", "paper", "--config", "default",
                 "--json", "--out", str(tmp_path)])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert set(result) == {"settings", "rows", "per_scene", "speedup_default_vs_paper", "goals"}
    settings = result["settings"]
    assert settings["markers"] == 256 and settings["image_shape"] == [480, 640]
    assert settings["blas_threads"] == "1" and settings["cv2_threads"] == 1
    assert set(settings["scenes"]) == set(bench_perception.SCENES)
    assert all(s["frames"] == 3 for s in settings["scenes"].values())
    assert [r["config"] for r in result["rows"]] == ["paper", "default"]
    for row in result["rows"]:
        assert set(bench_perception.TABLE_COLUMNS) <= set(row)
        for stage in bench_perception.STAGES:
            assert 0.0 < row[f"{stage}_ms_median"] <= row[f"{stage}_ms_p99"]
        assert row["total_ms_median"] >= row["detect_ms_median"]
        assert row["first_frame_ms_median"] > 0.0  # apart: its one-time set-up made the p99
        assert 0.0 <= row["tracking_rms_px"] < 1.0
        assert 0.9 < row["tracked_share"] <= 1.0
        assert 0.0 <= row["field_rmse_px"] < 2.0
        assert row["swaps"] == 0 and row["large_shear_swaps"] == 0
        assert row["frames"] == 2 * (len(bench_perception.SCENES) - 2)
    assert set(result["per_scene"]["default"]) == set(bench_perception.SCENES)
    speedup = result["speedup_default_vs_paper"]
    assert math.isfinite(speedup) and speedup > 0.0
    assert set(result["goals"]) == {"speedup_5x_equal_accuracy", "total_2ms", "clean_rms_0.1px", "no_swap_1.5_pitches"}
    no_swap = result["goals"].pop("no_swap_1.5_pitches")
    assert all(isinstance(goal["met"], bool) for goal in result["goals"].values())
    assert no_swap["met"] is None, "3 frames never reach 1.5 pitches per frame: not tested (it said MISSED)"
    table = (tmp_path / "perception_bench.md").read_text()
    assert table.startswith("| config |") and "| default |" in table
    for name in ("pareto_tracking_rms_px.png", "pareto_field_rmse_px.png", "perception_bench.json"):
        assert (tmp_path / name).stat().st_size > 0


@pytest.mark.parametrize(
    "argv, message",
    [
        (["perception", "--frames", "2"], "frames >= 3"),
        (["perception", "--config", "default"], "must include paper and default"),
        (["perception", "--config", "paper", "--config", "default", "--config", "nope"], "nope"),
    ],
)
def test_bad_request_fails_before_any_work(argv: list[str], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        _run(argv)
