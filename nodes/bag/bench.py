"""`fv bench bag`: record a camera-rate session and check every message is in the bag.

On a private bus (its own forwarder) this process publishes, at `--fps`, a mono8 frame
on /camera/image, a 30x30x3 DisplacementField on /field and a SlipState on /slip,
while `fv bag record` runs as a separate process. Reported: messages published vs
recorded per topic (recorded sequence numbers must be exactly 0..N-1), the recorder's
CPU use over the publishing window (from /proc, % of one core), bag size and write
rate; then the bag is played back with `fv bag play --fast` and the frames per second
a subscriber receives are reported.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from nodes.arg_types import positive_float, positive_int
from nodes.proc_stats import cpu_seconds
from nodes.process_stop import stop_process

TOPICS = ("/camera/image", "/field", "/slip")
N_DISTINCT_FRAMES = 16
CONNECT_TIMEOUT_S = 15.0
PLAY_IDLE_S = 1.0


def add_parser(kinds: argparse._SubParsersAction, name: str) -> None:
    p = kinds.add_parser(name, help="record frames + fields + slip at camera rate: completeness, recorder CPU, "
                                    "fast replay rate")
    p.add_argument("--duration", type=positive_float, default=60.0, metavar="S", help="seconds of publishing (default 60)")
    p.add_argument("--fps", type=positive_float, default=60.0, help="frames per second (default 60)")
    p.add_argument("--width", type=positive_int, default=640, help="frame width in px")
    p.add_argument("--height", type=positive_int, default=480, help="frame height in px")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd")
    p.add_argument("--keep", type=Path, help="keep the bag in this (new) folder")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=_bench_bag)


def _frames(width: int, height: int) -> list[Any]:
    """Camera-like mono8 frames: a grid of dark markers on a bright skin plus sensor noise."""
    import numpy as np
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:height, 0:width]
    base = 200.0 - 150.0 * ((np.hypot((xx % 40) - 20, (yy % 40) - 20) < 6))
    return [np.clip(base + rng.normal(0, 3, base.shape), 0, 255).astype(np.uint8) for _ in range(N_DISTINCT_FRAMES)]


def _publish(address: Any, duration_s: float, fps: float, width: int, height: int,
             on_start: Callable[[], None]) -> dict[str, int]:
    """Publish the three topics at `fps` for `duration_s` once the recorder subscribed
    (calling `on_start()` then); returns the messages sent per topic."""
    import numpy as np

    from msgs import DisplacementField, Image, SlipState
    from nodes.bus import PublisherSocket
    pub = PublisherSocket("bench_camera", address)
    try:
        pub.wait_connected(CONNECT_TIMEOUT_S)
        deadline = time.monotonic() + CONNECT_TIMEOUT_S
        while not all(pub.has_subscribers(t) for t in TOPICS):
            if time.monotonic() > deadline:
                raise RuntimeError(f"the recorder did not subscribe to {TOPICS} within {CONNECT_TIMEOUT_S} s")
            time.sleep(0.02)
        frames = _frames(width, height)
        grid = np.linspace(0, 600, 30, dtype=np.float32)
        rng = np.random.default_rng(1)
        n = int(duration_s * fps)
        on_start()
        t0 = time.monotonic()
        for i in range(n):
            time.sleep(max(0.0, t0 + i / fps - time.monotonic()))
            stamp = time.time_ns()
            pub.publish("/camera/image", Image(stamp_ns=stamp, data=frames[i % len(frames)]))
            field = rng.normal(0, 1, (30, 30, 3)).astype(np.float32)
            pub.publish("/field", DisplacementField(stamp_ns=stamp, field=field, grid_x_px=grid, grid_y_px=grid))
            pub.publish("/slip", SlipState(stamp_ns=stamp, probability=float(i % 10) / 10,
                                           window_stamps_ns=np.full(10, stamp, np.int64)))
        return {t: n for t in TOPICS}
    finally:
        pub.close()


def _check_bag(bag_dir: Path, published: dict[str, int]) -> dict[str, Any]:
    from nodes.bag.reader import BagReader
    bag = BagReader(bag_dir)
    seqs: dict[str, list[int]] = {t: [] for t in TOPICS}
    for m in bag.messages(list(TOPICS)):
        seqs[m.topic].append(m.sequence)
    missing = {t: len(set(range(published[t])) - set(s)) for t, s in seqs.items()}
    return {"recorded": {t: len(s) for t, s in seqs.items()}, "missing": missing,
            "complete": all(sorted(s) == list(range(published[t])) for t, s in seqs.items()),
            "bag_size_b": bag.size_b, "bag_files": len(bag.files), "bag_duration_s": bag.duration_s,
            "payload_b": bag.chunk_stats()["uncompressed_b"]}


def _fast_play(bag_dir: Path, env: dict[str, str], address: Any) -> dict[str, Any]:
    """Play the image topic with --fast; count what a subscriber receives."""
    from nodes.bus import TopicReader
    with TopicReader(["/camera/image"], address, hwm=100_000) as reader:
        proc = subprocess.Popen([sys.executable, "-m", "nodes.cli", "bag", "play", str(bag_dir), "--fast",
                                 "--topics", "/camera/image"], env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        try:
            times: list[float] = []
            while proc.poll() is None or times and time.monotonic() - times[-1] < PLAY_IDLE_S:
                if reader.recv_raw(0.2) is not None:
                    times.append(time.monotonic())
        finally:
            stop_process(proc)
    span = times[-1] - times[0] if len(times) > 1 else 0.0
    return {"received": len(times), "fps": (len(times) - 1) / span if span > 0 else 0.0}


def run_bench(duration_s: float, fps: float, width: int, height: int, compression: str,
              keep: Path | None = None) -> dict[str, Any]:
    """Run the benchmark on a private bus; returns the measurements (see module doc)."""
    from nodes.endpoints import BUS_ENV, bus_address
    from nodes.forwarder import ensure_forwarder
    tmp = Path(tempfile.mkdtemp(prefix="fvbag"))
    address = bus_address(f"ipc://{tmp}/bus")
    env = dict(os.environ, **{BUS_ENV: address.url})
    bag_dir = keep or tmp / "bench"
    forwarder = ensure_forwarder(address)
    recorder = None
    try:
        recorder = subprocess.Popen([sys.executable, "-m", "nodes.cli", "bag", "record", *TOPICS, "-o", str(bag_dir),
                                     "--compression", compression], env=env, stderr=subprocess.PIPE, text=True)
        start: list[float] = []  # recorder CPU s and wall time when publishing starts
        published = _publish(address, duration_s, fps, width, height,
                             lambda: start.extend((cpu_seconds(recorder.pid), time.monotonic())))
        cpu_s, wall_s = cpu_seconds(recorder.pid) - start[0], time.monotonic() - start[1]
        code = stop_process(recorder)
        log = recorder.stderr.read()
        if code != 0:
            raise RuntimeError(f"fv bag record exited with {code}: {log.strip()[-500:]}")
        result = {"duration_s": duration_s, "fps": fps, "frame": f"{width}x{height} mono8", "compression": compression,
                  "published": published, **_check_bag(bag_dir, published),
                  "publish_s": wall_s, "recorder_cpu_percent": 100.0 * cpu_s / wall_s,
                  "recorder_summary": log.strip().splitlines()[-1]}
        result["payload_MBps"] = result["payload_b"] / 1e6 / wall_s  # as published: a rate the publisher could
        # not keep up with (fps 20000) took 11.8 s for a 1 s duration_s, and per duration_s read 12 times too high
        result["fast_play"] = _fast_play(bag_dir, env, address)
        return result
    finally:
        if recorder is not None:
            stop_process(recorder, signal.SIGKILL)
        if forwarder is not None:
            stop_process(forwarder, signal.SIGTERM)
        shutil.rmtree(tmp, ignore_errors=True)


def _bench_bag(args: argparse.Namespace) -> int:
    if args.keep is not None and args.keep.exists():  # the recorder refuses it: the bench waited 15 s, then said so
        raise ValueError(f"--keep {args.keep} exists: give a new folder")
    if int(args.duration * args.fps) < 1:  # it said the bag "has no topic '/camera/image'"
        raise ValueError(f"--duration {args.duration} s at --fps {args.fps} publishes no frame")
    r = run_bench(args.duration, args.fps, args.width, args.height, args.compression, args.keep)
    if args.json:
        print(json.dumps(r, indent=2))
    else:
        print(f"recorded {r['recorded']} of {r['published']} published ({'complete' if r['complete'] else 'MISSING'} "
              f"{r['missing']}); recorder CPU {r['recorder_cpu_percent']:.1f} % of a core; bag "
              f"{r['bag_size_b'] / 1e6:.1f} MB for {r['payload_MBps']:.1f} MB/s of payload; fast replay "
              f"{r['fast_play']['fps']:.0f} frames/s ({r['fast_play']['received']} received)")
    return 0 if r["complete"] else 1
