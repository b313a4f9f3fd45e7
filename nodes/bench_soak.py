"""`fv bench soak`: the default pipeline for a long run (default 30 minutes at 60 FPS), with
nodes killed on purpose, to show it can run for hours (issue #8).

The pipeline is `launch/pipeline.yaml` with the default configuration on a private bus,
the camera replaying a pre-rendered scene (see `nodes.bench_pipeline`). Every `sample_s`
the resident memory of every process is read from /proc; every `/slip` is counted per
minute (a last, partial minute over its own length), each minute's rate checked against
`GOAL_SLIP_SHARE` of the camera's; NodeStatus gives the queue drops and the slip detector's skipped decisions. Every
`kill_every_s` one node (tracker, interpolator, slip_detector in turn) gets SIGKILL; the
launcher respawns it and the recovery time is the time from the kill to the first `/slip`
judging a frame captured after the kill.

Memory growth of a process is the median resident size of its last `GROWTH_SPAN` of
samples over the median of its first `GROWTH_SPAN` after `WARMUP_S` (a respawned process
starts a new series; warm-up: `WARMUP_S`, at most a fifth of the run). The report lists the per-minute `/slip` rates, drops, skipped
decisions and every recovery.
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import signal
import time
from typing import Any

import numpy as np

from nodes.arg_types import non_negative_float, positive_float, positive_int
from nodes.bench_pipeline import pipeline_args, pipeline_launch, process_ids
from nodes.shipped_models import model_help

VICTIMS = ("tracker", "interpolator", "slip_detector")
WARMUP_S = 60.0  # at most this much of each process series is left out as warm-up (<= 1/5 of the run)
GROWTH_SPAN = 0.1  # share of a process's samples at each end compared for its growth
MIN_SERIES_SHARE = 0.3  # a series shorter than this share of the run gets no growth figure
GOAL_GROWTH_PERCENT = 1.0
GOAL_RECOVERY_S = 2.0
KILL_MARGIN_S = 15.0  # no kill this close to the end: its recovery must be seen
GOAL_SLIP_SHARE = 0.9  # every minute's /slip rate at least this share of the camera's
MIN_RATE_SPAN_S = 10.0  # a last, partial minute shorter than this gets no rate (too few decisions to count)


def per_minute_rates(counts: dict[int, int], run_s: float) -> list[float]:
    """/slip rates (Hz) of each minute of a run of `run_s` seconds from `counts` (minute index -> decisions),
    the last, partial minute over its own length (a run under a minute has that one), unless it is shorter
    than MIN_RATE_SPAN_S and not the only one."""
    spans = [min(60.0, run_s - 60.0 * m) for m in range(math.ceil(run_s / 60.0))]
    if len(spans) > 1 and spans[-1] < MIN_RATE_SPAN_S:
        spans.pop()
    return [counts.get(m, 0) / span for m, span in enumerate(spans)]


def memory_growth(series: dict[tuple[str, int], list[tuple[float, int]]], run_s: float) -> list[dict[str, Any]]:
    """Growth (%) of each (node, pid) series of (t_s, rss_bytes) samples over a run of
    `run_s` seconds (see module doc)."""
    warmup_s = min(WARMUP_S, run_s / 5)
    rows = []
    for (name, pid), samples in sorted(series.items()):
        kept = [(t, rss) for t, rss in samples if t - samples[0][0] >= warmup_s]
        if len(kept) < 10 or kept[-1][0] - kept[0][0] < MIN_SERIES_SHARE * run_s:
            continue
        k = max(1, int(len(kept) * GROWTH_SPAN))
        first = float(np.median([rss for _, rss in kept[:k]]))
        last = float(np.median([rss for _, rss in kept[-k:]]))
        rows.append({"node": name, "pid": pid, "span_s": round(kept[-1][0] - kept[0][0], 1),
                     "rss_mb_first": round(first / 1e6, 2), "rss_mb_last": round(last / 1e6, 2),
                     "growth_percent": round(100.0 * (last - first) / first, 3)})
    return rows


def run_soak(minutes: float, fps: float, kill_every_s: float, sample_s: float, threads: int,
             log: Any, model: str | None = None) -> dict[str, Any]:
    """Run the soak and return its report (see module doc); `model` replaces the default
    configuration's slip model."""
    from nodes.proc_stats import memory_bytes

    args = pipeline_args("default", fps, threads)
    if model:
        args["model"] = model
    series: dict[tuple[str, int], list[tuple[float, int]]] = {}
    per_minute: dict[int, int] = {}
    last_status: dict[tuple[str, int], Any] = {}
    kills: list[dict[str, Any]] = []
    victims = itertools.cycle(VICTIMS)
    with pipeline_launch(args, log) as (launch, reader):
        t0 = time.monotonic()
        end = t0 + 60.0 * minutes
        next_sample, next_kill = t0, (t0 + kill_every_s if kill_every_s > 0 else float("inf"))
        pending: dict[str, Any] | None = None
        while (now := time.monotonic()) < end:
            item = reader.recv(min(0.1, end - now))
            if item is not None and item.topic == "/slip":
                minute = int((time.monotonic() - t0) // 60)
                per_minute[minute] = per_minute.get(minute, 0) + 1
                if pending is not None and item.msg.stamp_ns > pending["kill_ns"]:
                    pending["recovery_s"] = round(time.monotonic() - pending["t"], 3)
                    kills.append({k: v for k, v in pending.items() if k not in ("t", "kill_ns")})
                    pending = None
            elif item is not None and item.topic == "/status":
                last_status[(item.msg.node, item.msg.pid)] = item.msg
            now = time.monotonic()
            if now >= next_sample:
                next_sample += sample_s
                for name, pid in process_ids(launch).items():
                    try:
                        series.setdefault((name, pid), []).append((now - t0, memory_bytes(pid)[0]))
                    except (OSError, TypeError):  # between a kill and the respawn
                        pass
            if now >= next_kill and pending is None and end - now > KILL_MARGIN_S:
                next_kill += kill_every_s
                victim = next(victims)
                pid = launch.pid(victim)
                if pid is not None:
                    pending = {"node": victim, "at_s": round(now - t0, 1), "t": now, "kill_ns": time.time_ns()}
                    os.kill(pid, signal.SIGKILL)
        if pending is not None:
            kills.append({"node": pending["node"], "at_s": pending["at_s"], "recovery_s": None})
    minutes_done = per_minute_rates(per_minute, 60.0 * minutes)
    growth = memory_growth(series, 60.0 * minutes)
    statuses = list(last_status.values())
    recoveries = [k["recovery_s"] for k in kills]
    return {
        "minutes": minutes, "fps": fps, "threads": threads, "model": args["model"],
        "slip_hz_per_minute": [round(v, 2) for v in minutes_done],
        "slip_hz_min": round(min(minutes_done), 2) if minutes_done else None,
        "slip_hz_max": round(max(minutes_done), 2) if minutes_done else None,
        "queue_drops": sum(s.drops for s in statuses if s.node in VICTIMS),
        "sequence_gaps": sum(s.gaps for s in statuses if s.node in VICTIMS),
        "skipped_decisions": sum(int(s.counters.get("skipped", 0)) for s in statuses if s.node == "slip_detector"),
        "memory": growth,
        "max_growth_percent": max((r["growth_percent"] for r in growth), default=None),
        "kills": kills, "recovered": sum(r is not None for r in recoveries),
        "max_recovery_s": max((r for r in recoveries if r is not None), default=None),
        "checks": {
            "memory_flat": all(r["growth_percent"] < GOAL_GROWTH_PERCENT for r in growth),
            "recovered_within_2s": all(r is not None and r <= GOAL_RECOVERY_S for r in recoveries),
            "slip_rate_steady": bool(minutes_done) and min(minutes_done) >= GOAL_SLIP_SHARE * fps,
        },
        "load_average": os.getloadavg(),
    }


def add_parser(kinds: argparse._SubParsersAction, name: str) -> None:
    p = kinds.add_parser(name, help="the default pipeline for a long run: memory, /slip rate, drops, kill + respawn")
    p.add_argument("--minutes", type=positive_float, default=30.0, help="run length (default 30)")
    p.add_argument("--fps", type=positive_float, default=60.0, help="camera rate in Hz (default 60)")
    p.add_argument("--kill-every", type=non_negative_float, default=600.0,
                   help="seconds between SIGKILLs of a node, in turn tracker, interpolator, slip_detector (0 = none)")
    p.add_argument("--sample", type=positive_float, default=5.0, help="seconds between memory samples (default 5)")
    p.add_argument("--threads", type=positive_int, default=1, help="torch threads of the slip detector (default 1)")
    p.add_argument("--model", default=None, help=f"slip model instead of the default configuration's: {model_help()}")
    p.add_argument("--log", default=os.devnull, help="write the nodes' output here (default: discarded)")
    p.add_argument("--json", action="store_true", help="print the report as JSON (default: a summary)")
    p.set_defaults(func=_bench_soak)


def _bench_soak(args: argparse.Namespace) -> int:
    if 2 * args.sample > 60 * args.minutes:  # the memory check compares samples: no pair, no check
        raise ValueError(f"--sample {args.sample} s: a run of --minutes {args.minutes} needs two samples at least")
    with open(args.log, "w") as log:
        report = run_soak(args.minutes, args.fps, args.kill_every, args.sample, args.threads, log, args.model)
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        print(f"/slip {report['slip_hz_min']}..{report['slip_hz_max']} Hz per minute; max memory growth "
              f"{report['max_growth_percent']} %; {report['recovered']}/{len(report['kills'])} kills recovered, "
              f"slowest {report['max_recovery_s']} s; checks {report['checks']}")
    return 0
