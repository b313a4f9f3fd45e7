"""`fv bench pipeline`: the four-process pipeline (camera, tracker, interpolator,
slip_detector) launched from `launch/pipeline.yaml` on a private bus, at several camera
rates, in the paper-faithful and the default configuration in the same run (issue #8).

The simulated camera replays a pre-rendered scene from memory (`prerender:=true`), so the
benchmark measures the pipeline, not the renderer: on a robot the camera driver costs
next to nothing. Rates and configurations are interleaved (for each rate, every
configuration) so load drifts on a shared machine hit them alike.

Measured per run, over `duration_s` after the first `/slip` and `warmup_s`:
- rates (Hz) of the camera (from its NodeStatus frame counter), `/markers`, `/field`, `/slip`;
- dropped frames per stage: messages the node's keep-last queue dropped plus sequence gaps
  (from NodeStatus), and the slip detector's skipped decisions (fields it took into its
  window but did not judge because a newer one waited);
- latency from header stamps: capture -> `/markers` published (camera + transport +
  tracker), `/markers` -> `/field`, `/field` -> `/slip`, and capture -> `/slip` received by
  a subscriber (what a gripper controller sees), p50 / p99 / max in ms;
- CPU per process (% of one core, from /proc) and peak resident memory (MB).
The report's ratios are each configuration's sustained `/slip` rate over the
paper-faithful one's at the highest camera rate, measured in the same run. `default` is
`launch/pipeline.yaml`'s defaults (default perception, the CNN+LSTM `sim_cnn_lstm`);
`paper_model` the default perception with the paper's ConvLSTM `sim`, to show the model's share.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from nodes.arg_types import non_negative_float, output_folder, positive_float, positive_int

REPO = Path(__file__).resolve().parent.parent
PIPELINE = REPO / "launch" / "pipeline.yaml"
SCENE = REPO / "launch" / "scenes" / "press_shear_slide.yaml"
CONFIGS: dict[str, dict[str, str]] = {
    "paper": {"preset": "paper", "field": "rbf_refit", "model": "sim"},
    "default": {"preset": "default", "field": "rbf_operator", "model": "sim_cnn_lstm"},
    "paper_model": {"preset": "default", "field": "rbf_operator", "model": "sim"},
}
PIPELINE_NODES = ("camera", "tracker", "interpolator", "slip_detector")
STAGE_TOPICS = ("/markers", "/field", "/slip")
FIRST_SLIP_TIMEOUT_S = 90.0
TABLE_COLUMNS = ("config", "fps", "camera_hz", "slip_hz", "dropped_total", "skipped", "latency_p50_ms",
                 "latency_p99_ms", "cpu_percent_total", "peak_rss_mb_total")


@dataclass
class Record:
    """Header stamps (ns) of the messages seen during the measured window, per topic:
    topic -> {capture stamp: (publish ns, receive ns)}."""

    stamps: dict[str, dict[int, tuple[int, int]]] = field(default_factory=lambda: {t: {} for t in STAGE_TOPICS})
    status: dict[str, Any] = field(default_factory=dict)


def percentiles_ms(values_ns: list[int]) -> dict[str, float | None]:
    """p50 / p99 / max of durations given in ns, in ms (None when there are none)."""
    if not values_ns:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    a = np.asarray(values_ns, np.float64) / 1e6
    return {"p50": round(float(np.percentile(a, 50)), 3), "p99": round(float(np.percentile(a, 99)), 3),
            "max": round(float(a.max()), 3), "n": int(a.size)}


def stage_latencies(rec: Record) -> dict[str, dict[str, float | None]]:
    """Per-stage and end-to-end latency from the recorded stamps (see module doc)."""
    markers, fields, slips = (rec.stamps[t] for t in STAGE_TOPICS)
    return {
        "capture_to_markers": percentiles_ms([pub - stamp for stamp, (pub, _) in markers.items()]),
        "markers_to_field": percentiles_ms([fields[s][0] - pub for s, (pub, _) in markers.items() if s in fields]),
        "field_to_slip": percentiles_ms([slips[s][0] - pub for s, (pub, _) in fields.items() if s in slips]),
        "capture_to_slip": percentiles_ms([recv - stamp for stamp, (_, recv) in slips.items()]),
    }


def _counter_delta(first: Any, last: Any, key: str) -> int:
    return int(last.counters.get(key, 0)) - int(first.counters.get(key, 0))


@contextlib.contextmanager
def pipeline_launch(args: dict[str, Any], log: io.TextIOBase) -> Iterator[tuple[Any, Any]]:
    """Launch `launch/pipeline.yaml` with `args` on a private bus (its own FV_BUS and
    forwarder) and a reader of `STAGE_TOPICS` and `/status`; yields (launch, reader) once
    the first `/slip` arrived, stops everything on exit."""
    from nodes.bus import TopicReader
    from nodes.endpoints import BUS_ENV, bus_address
    from nodes.launcher import Launch

    folder = Path(tempfile.mkdtemp(prefix="fvpb", dir="/tmp"))  # IPC paths must stay short
    old_bus = os.environ.get(BUS_ENV)
    os.environ[BUS_ENV] = bus_address(f"ipc://{folder}/bus").url
    launch = Launch.from_file(PIPELINE, args, output=log)
    reader = TopicReader([*STAGE_TOPICS, "/status"])
    try:
        launch.start()
        deadline = time.monotonic() + FIRST_SLIP_TIMEOUT_S
        while (item := reader.recv(max(0.0, deadline - time.monotonic()))) is None or item.topic != "/slip":
            if item is None:
                raise RuntimeError(f"pipeline {args}: no /slip within {FIRST_SLIP_TIMEOUT_S:g} s")
        yield launch, reader
    finally:
        reader.close()
        launch.stop()
        if old_bus is None:
            os.environ.pop(BUS_ENV, None)
        else:
            os.environ[BUS_ENV] = old_bus
        shutil.rmtree(folder, ignore_errors=True)


def pipeline_args(config: str, fps: float, threads: int) -> dict[str, Any]:
    """`launch/pipeline.yaml` arguments of configuration `config` at `fps`, the camera
    replaying the pre-rendered benchmark scene."""
    return dict(CONFIGS[config], fps=fps, scene=str(SCENE), prerender=True, threads=threads)


def process_ids(launch: Any) -> dict[str, int]:
    """name -> pid of the pipeline's node processes and of the forwarder the launch started."""
    pids = {name: launch.pid(name) for name in PIPELINE_NODES}
    if launch.forwarder_pid is not None:
        pids["forwarder"] = launch.forwarder_pid
    return pids


def run_once(config: str, fps: float, duration_s: float, warmup_s: float, threads: int,
             log: io.TextIOBase) -> dict[str, Any]:
    """Launch the pipeline with `CONFIGS[config]` at `fps` on a private bus and measure it."""
    from nodes.proc_stats import cpu_seconds, memory_bytes

    with pipeline_launch(pipeline_args(config, fps, threads), log) as (launch, reader):
        pids = process_ids(launch)
        warm_end = time.monotonic() + warmup_s
        first_status: dict[str, Any] = {}
        while time.monotonic() < warm_end:
            item = reader.recv(0.1)
            if item is not None and item.topic == "/status":
                first_status[item.msg.node] = item.msg
        rec = Record()
        cpu0 = {name: cpu_seconds(pid) for name, pid in pids.items()}
        t0 = time.monotonic()
        end = t0 + duration_s
        while (now := time.monotonic()) < end:
            item = reader.recv(end - now)
            if item is None:
                continue
            recv_ns = time.time_ns()
            msg = item.msg
            if item.topic == "/status":
                rec.status[msg.node] = msg
                first_status.setdefault(msg.node, msg)
            else:
                rec.stamps[item.topic][msg.stamp_ns] = (msg.pub_ns, recv_ns)
        wall = time.monotonic() - t0
        cpu = {name: round(100.0 * (cpu_seconds(pid) - cpu0[name]) / wall, 1) for name, pid in pids.items()}
        peak = {name: round(memory_bytes(pid)[1] / 1e6, 1) for name, pid in pids.items()}
        respawned = [name for name in PIPELINE_NODES if launch.pid(name) != pids[name]]
    return summarise(config, fps, wall, rec, first_status, cpu, peak, respawned)


def summarise(config: str, fps: float, wall_s: float, rec: Record, first_status: dict[str, Any],
              cpu: dict[str, float], peak: dict[str, float], respawned: list[str]) -> dict[str, Any]:
    """One run's report row from what was recorded."""
    last = rec.status
    cam0, cam1 = first_status.get("camera"), last.get("camera")
    camera_hz = None
    if cam0 is not None and cam1 is not None and cam1.uptime_s > cam0.uptime_s:
        camera_hz = round(_counter_delta(cam0, cam1, "frames") / (cam1.uptime_s - cam0.uptime_s), 2)
    dropped = {}
    for name in ("tracker", "interpolator", "slip_detector"):
        if name in first_status and name in last:
            a, b = first_status[name], last[name]
            dropped[name] = (b.drops + b.gaps) - (a.drops + a.gaps)
    skipped = (_counter_delta(first_status["slip_detector"], last["slip_detector"], "skipped")
               if "slip_detector" in first_status and "slip_detector" in last else None)
    rates = {t.strip("/") + "_hz": round(len(rec.stamps[t]) / wall_s, 2) for t in STAGE_TOPICS}
    latency = stage_latencies(rec)
    return {"config": config, **CONFIGS[config], "fps": fps, "duration_s": round(wall_s, 2),
            "camera_hz": camera_hz, **rates, "dropped": dropped, "dropped_total": sum(dropped.values()),
            "skipped": skipped, "latency_ms": latency, "latency_p50_ms": latency["capture_to_slip"]["p50"],
            "latency_p99_ms": latency["capture_to_slip"]["p99"], "cpu_percent": cpu,
            "cpu_percent_total": round(sum(cpu.values()), 1), "peak_rss_mb": peak,
            "peak_rss_mb_total": round(sum(peak.values()), 1), "respawned": respawned}


def run_bench(rates: list[float], configs: list[str], duration_s: float, warmup_s: float, threads: int,
              log: io.TextIOBase) -> dict[str, Any]:
    """Every configuration at every rate (rates outer, configurations inner) and the ratio."""
    runs = []
    for fps in rates:
        for config in configs:
            runs.append(run_once(config, fps, duration_s, warmup_s, threads, log))
            r = runs[-1]
            log.write(f"[bench] {config} @ {fps:g} FPS: /slip {r['slip_hz']} Hz, p99 {r['latency_p99_ms']} ms\n")
            log.flush()
    top = max(rates)
    by_config = {r["config"]: r for r in runs if r["fps"] == top}
    paper_hz = by_config["paper"]["slip_hz"] if "paper" in by_config else 0.0
    ratios = {f"{name}_over_paper_slip_hz": round(r["slip_hz"] / paper_hz, 2)
              for name, r in by_config.items() if name != "paper" and paper_hz > 0}
    return {"runs": runs, "ratios": ratios, "ratio_at_fps": top,
            "load_average": os.getloadavg(), "threads": threads}


def add_parser(kinds: argparse._SubParsersAction, name: str) -> None:
    p = kinds.add_parser(name, help="the four-process pipeline at several camera rates, paper vs default")
    p.add_argument("--fps", default="30,60,120", help="comma-separated camera rates in Hz (default 30,60,120)")
    p.add_argument("--configs", default="paper,default", help=f"comma-separated among {sorted(CONFIGS)} (default paper,default)")
    p.add_argument("--duration", type=positive_float, default=20.0, help="measured seconds per run (default 20)")
    p.add_argument("--warmup", type=non_negative_float, default=3.0, help="seconds after the first /slip before measuring")
    p.add_argument("--threads", type=positive_int, default=1, help="torch threads of the slip detector (default 1)")
    p.add_argument("--log", type=Path, default=None, help="write the nodes' output here (default: discarded)")
    p.add_argument("--out", type=output_folder, default=None,
                   help="also write report.json, table.md and pipeline.png here")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_bench_pipeline)


def _bench_pipeline(args: argparse.Namespace) -> int:
    from nodes.plots import curve_plot, markdown_table
    rates = [float(v) for v in args.fps.split(",") if v]
    configs = [c for c in args.configs.split(",") if c]
    unknown = sorted(set(configs) - set(CONFIGS))
    if unknown or not configs:
        raise ValueError(f"--configs: unknown {unknown or configs}; known: {sorted(CONFIGS)}")
    if not rates or min(rates) <= 0:
        raise ValueError(f"--fps: rates must be > 0, got {args.fps!r}")
    with open(args.log or os.devnull, "w") as log:
        report = run_bench(rates, configs, args.duration, args.warmup, args.threads, log)
    table = markdown_table(report["runs"], TABLE_COLUMNS)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "report.json").write_text(json.dumps(report, indent=1) + "\n")
        (args.out / "table.md").write_text(table + "\n")
        series = {f"{c} {key}": ([r["fps"] for r in report["runs"] if r["config"] == c],
                                 [r[key] or 0.0 for r in report["runs"] if r["config"] == c])
                  for c in configs for key in ("slip_hz",)}
        series["camera rate"] = (rates, rates)
        curve_plot(series, args.out / "pipeline.png", title="Slip decisions per second vs camera rate",
                   x_label="camera rate (FPS)", y_label="/slip rate (Hz)")
    print(json.dumps(report, indent=1) if args.json else table)
    return 0
