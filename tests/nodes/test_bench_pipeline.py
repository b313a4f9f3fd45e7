"""`fv bench pipeline` and `fv bench soak`: latency and growth arithmetic on known
stamps, and one short real run of the four-process pipeline."""
from __future__ import annotations

import json
from pathlib import Path

from nodes.bench_pipeline import Record, percentiles_ms, stage_latencies
from nodes.bench_soak import memory_growth, per_minute_rates
from tests.nodes.conftest import run_fv

MS = 1_000_000


def test_stage_latencies_follow_one_frame_through_the_stages() -> None:
    rec = Record()
    for k in range(100):
        stamp = 1_000 * MS + k * 33 * MS
        rec.stamps["/markers"][stamp] = (stamp + 3 * MS, stamp + 4 * MS)
        rec.stamps["/field"][stamp] = (stamp + 5 * MS, stamp + 6 * MS)
        if k % 2 == 0:  # the slip detector judged every other window
            rec.stamps["/slip"][stamp] = (stamp + 15 * MS, stamp + 16 * MS)
    lat = stage_latencies(rec)
    assert lat["capture_to_markers"]["p50"] == 3.0
    assert lat["markers_to_field"]["p50"] == 2.0
    assert lat["field_to_slip"] == {"p50": 10.0, "p99": 10.0, "max": 10.0, "n": 50}
    assert lat["capture_to_slip"]["p99"] == 16.0


def test_percentiles_of_nothing_are_none() -> None:
    assert percentiles_ms([]) == {"p50": None, "p99": None, "max": None, "n": 0}


def test_memory_growth_per_process_series() -> None:
    run_s = 1000.0
    flat = [(t, 100 * 2**20) for t in range(0, 1000, 5)]
    leaking = [(t, int((100 + 0.01 * t) * 2**20)) for t in range(0, 1000, 5)]
    short = [(t, 50 * 2**20) for t in range(900, 1000, 5)]  # a respawned process near the end
    rows = {r["node"]: r for r in memory_growth({("flat", 1): flat, ("leak", 2): leaking, ("short", 3): short}, run_s)}
    assert rows["flat"]["growth_percent"] == 0.0
    assert 7.0 < rows["leak"]["growth_percent"] < 9.0  # ~100 MB -> ~109 MB after the warm-up minute
    assert "short" not in rows


def test_slip_rates_per_minute_count_a_partial_last_minute() -> None:
    """Only whole minutes had a rate: a 0.4 minute soak reported none (`/slip None..None Hz`)."""
    assert per_minute_rates({0: 1440}, 24.0) == [60.0]
    assert per_minute_rates({0: 3600, 1: 900}, 75.0) == [60.0, 60.0]  # 15 s of the second minute
    assert per_minute_rates({0: 3600, 1: 30}, 61.0) == [60.0]  # 1 s: too short to count
    assert per_minute_rates({1: 3000}, 120.0) == [0.0, 50.0]


def test_bench_pipeline_short_run_reports_every_stage(tmp_path: Path) -> None:
    out = run_fv("bench", "pipeline", "--fps", "20", "--configs", "default", "--duration", "3", "--warmup", "1",
                 "--json", "--out", str(tmp_path), timeout_s=150.0)
    assert out.returncode == 0, out.stderr[-2000:]
    run = json.loads(out.stdout)["runs"][0]
    assert run["config"] == "default" and run["fps"] == 20.0
    assert run["markers_hz"] > 5 and run["field_hz"] > 5 and run["slip_hz"] > 1
    assert set(run["cpu_percent"]) >= {"camera", "tracker", "interpolator", "slip_detector"}
    assert all(v > 0 for v in run["peak_rss_mb"].values())
    lat = run["latency_ms"]
    assert 0 < lat["capture_to_markers"]["p50"] <= lat["capture_to_slip"]["p50"]
    assert run["respawned"] == []
    row = (tmp_path / "table.md").read_text().splitlines()[-1].split("|")
    assert row[5].strip() == str(run["dropped_total"])  # a dict of the stages' drops was printed there


def test_bench_pipeline_rejects_an_unknown_configuration() -> None:
    out = run_fv("bench", "pipeline", "--configs", "fastest_ever", timeout_s=30.0)
    assert out.returncode == 2 and "fastest_ever" in out.stderr
