"""`fv bench bus`: latency and throughput of camera-sized `Image` frames through the
forwarder, against a direct pyzmq connection measured in the same run.

Both paths use the same processes and code: a publisher process (`PublisherSocket`,
zero-copy sends) and a subscriber process (SUB socket, `parse_envelope` + `msgs.decode`,
as every subscriber does). "raw": the publisher connects straight to the subscriber's
bound SUB socket. "forwarder": both connect to a forwarder process (`fv forwarder`).

Latency (receive time - `pub_ns`) is measured at a paced rate so no queue builds up.
Throughput: the publisher offers frames at a fixed high rate (`--offered-rate`, above
the goal) and the subscriber's receive rate is what the path carries; frames the path
cannot carry are dropped at a high-water mark and reported as lost. (A flat-out
publisher would measure how the CPU is shared between the processes instead.)
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import tempfile
import time
from typing import Any

import numpy as np

from nodes.arg_types import positive_float, positive_int

TOPIC = "/bench"
GOAL_ADDED_P50_MS = 0.3
GOAL_THROUGHPUT_FPS = 2000.0
IDLE_END_S = 2.0


def _subscriber(endpoint: str, bind: bool, ready: Any, results: Any) -> None:
    """Receive until an "end" frame (or `IDLE_END_S` of silence); put the measurements
    on `results`: latencies of "lat" frames (ms) and receive times of "tp" frames (ns)."""
    import zmq

    import msgs
    from nodes.bus import LINGER_MS, parse_envelope, subscription_prefixes

    ctx = zmq.Context()
    sock = ctx.socket(zmq.SUB)
    sock.linger = LINGER_MS
    sock.rcvhwm = 1000
    for prefix in subscription_prefixes(TOPIC):
        sock.setsockopt(zmq.SUBSCRIBE, prefix)
    if bind:
        sock.bind(endpoint)
    else:
        sock.connect(endpoint)
    ready.set()
    latency_ms: list[float] = []
    tp_ns: list[int] = []
    while sock.poll(int(IDLE_END_S * 1000)):
        frames = sock.recv_multipart(copy=False)
        now = time.time_ns()
        topic, _node, _latched = parse_envelope(frames[0])
        msg = msgs.decode(frames[1:], topic)
        if msg.frame_id == "lat":
            latency_ms.append((now - msg.pub_ns) / 1e6)
        elif msg.frame_id == "tp":
            tp_ns.append(now)
        elif msg.frame_id == "end":
            break
    sock.close()
    ctx.term()
    results.put({"latency_ms": latency_ms, "tp_ns": tp_ns})


def _publisher(endpoint: str, width: int, height: int, n_latency: int, rate_hz: float, n_throughput: int,
               offered_fps: float, results: Any) -> None:
    """Wait for the subscriber, send `n_latency` frames at `rate_hz`, then
    `n_throughput` frames at `offered_fps`, then "end" frames; put the send rate on `results`."""
    from msgs import Image
    from nodes.bus import PublisherSocket
    from nodes.endpoints import BusAddress

    sock = PublisherSocket("bench_pub", BusAddress(endpoint, endpoint, "", ""))
    deadline = time.monotonic() + 10.0
    while not sock.has_subscribers(TOPIC):
        if time.monotonic() > deadline:
            raise RuntimeError(f"bench subscriber never subscribed at {endpoint}")
        time.sleep(0.01)
    time.sleep(0.1)
    frame = np.random.default_rng(0).integers(0, 256, (height, width), dtype=np.uint8)
    msg = Image(encoding="mono8", data=frame, frame_id="lat")
    _paced(sock, msg, n_latency, rate_hz)
    time.sleep(0.2)
    msg.frame_id = "tp"
    t0 = time.perf_counter()
    _paced(sock, msg, n_throughput, offered_fps)
    send_s = time.perf_counter() - t0
    time.sleep(0.5)
    end = Image(encoding="mono8", data=np.zeros((1, 1), np.uint8), frame_id="end")
    for _ in range(3):
        sock.publish(TOPIC, end)
        time.sleep(0.05)
    sock.close()
    results.put({"send_fps": n_throughput / send_s})


def _paced(sock: Any, msg: Any, count: int, rate_hz: float) -> None:
    """Publish `msg` `count` times at `rate_hz` (stamping each), catching up after a late wake-up."""
    next_t = time.monotonic()
    for _ in range(count):
        msg.stamp_ns = time.time_ns()
        sock.publish(TOPIC, msg)
        next_t += 1.0 / rate_hz
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def _run_path(name: str, pub_endpoint: str, sub_endpoint: str, bind_sub: bool, opts: argparse.Namespace) -> dict:
    ctx = mp.get_context("spawn")
    ready, sub_q, pub_q = ctx.Event(), ctx.Queue(), ctx.Queue()
    sub = ctx.Process(target=_subscriber, args=(sub_endpoint, bind_sub, ready, sub_q), name=f"bench-sub-{name}")
    sub.start()
    if not ready.wait(20.0):
        sub.kill()
        raise RuntimeError(f"bench subscriber ({name}) did not start")
    pub = ctx.Process(target=_publisher, args=(pub_endpoint, opts.width, opts.height, opts.frames, opts.rate,
                                                opts.throughput_frames, opts.offered_rate, pub_q), name=f"bench-pub-{name}")
    pub.start()
    try:
        sent = pub_q.get(timeout=60.0)
        got = sub_q.get(timeout=60.0)
    finally:
        for proc in (pub, sub):
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
    lat = np.asarray(got["latency_ms"])
    tp = np.asarray(got["tp_ns"])
    span_s = (tp[-1] - tp[0]) / 1e9 if tp.size > 1 else float("nan")
    return {
        "latency_ms": {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)),
                       "mean": float(lat.mean()), "n": int(lat.size)} if lat.size else {"n": 0},
        "throughput_fps": float((tp.size - 1) / span_s) if tp.size > 1 else 0.0,
        "throughput_received": int(tp.size),
        "throughput_sent": opts.throughput_frames,
        "send_fps": sent["send_fps"],
    }


def run_bench(opts: argparse.Namespace) -> dict[str, Any]:
    """Measure the raw path and the forwarder path; the `fv bench bus` result."""
    from nodes.endpoints import bus_address
    from nodes.forwarder import ensure_forwarder

    folder = tempfile.mkdtemp(prefix="fvbench", dir="/tmp")  # IPC paths must stay short
    forwarder = None
    try:
        raw = _run_path("raw", f"ipc://{folder}/raw", f"ipc://{folder}/raw", True, opts)
        address = bus_address(f"ipc://{folder}/bus")
        forwarder = ensure_forwarder(address)
        fwd = _run_path("forwarder", address.pub, address.sub, False, opts)
    finally:
        if forwarder is not None:
            forwarder.terminate()
            forwarder.wait(5.0)
        shutil.rmtree(folder, ignore_errors=True)
    added = fwd["latency_ms"]["p50"] - raw["latency_ms"]["p50"]
    return {
        "frame": {"width": opts.width, "height": opts.height, "encoding": "mono8", "bytes": opts.width * opts.height},
        "latency_rate_hz": opts.rate, "offered_fps": opts.offered_rate, "cpus": os.cpu_count(),
        "loadavg_1min": os.getloadavg()[0],
        "raw": raw, "forwarder": fwd,
        "forwarder_added_p50_ms": added,
        "goal": {"added_p50_ms_max": GOAL_ADDED_P50_MS, "throughput_fps_min": GOAL_THROUGHPUT_FPS,
                 "met": bool(added <= GOAL_ADDED_P50_MS and fwd["throughput_fps"] >= GOAL_THROUGHPUT_FPS)},
    }


def add_parser(kinds: argparse._SubParsersAction, name: str) -> None:
    """Add `fv bench NAME` (an entry of nodes.bench_commands.BENCHMARKS)."""
    p = kinds.add_parser(name, help="Image latency and throughput through the forwarder vs raw pyzmq")
    p.add_argument("--width", type=positive_int, default=640, help="frame width in px")
    p.add_argument("--height", type=positive_int, default=480, help="frame height in px")
    p.add_argument("--frames", type=positive_int, default=300, help="frames for the latency measurement")
    p.add_argument("--rate", type=positive_float, default=200.0, help="frames per second during the latency measurement")
    p.add_argument("--throughput-frames", type=positive_int, default=6000, help="frames offered for the throughput measurement")
    p.add_argument("--offered-rate", type=positive_float, default=3000.0, help="frames per second offered for throughput")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=_bench_bus)


def _bench_bus(args: argparse.Namespace) -> int:
    if args.throughput_frames < 2:  # a rate needs two frames: one gave "throughput_fps": 0.0
        raise ValueError(f"--throughput-frames {args.throughput_frames}: a throughput needs 2 frames at least")
    result = run_bench(args)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    for name in ("raw", "forwarder"):
        r = result[name]
        print(f"{name:>9}: latency p50 {r['latency_ms']['p50']:.3f} ms  p99 {r['latency_ms']['p99']:.3f} ms  "
              f"throughput {r['throughput_fps']:.0f} frames/s ({r['throughput_received']}/{r['throughput_sent']} "
              f"received, sent at {r['send_fps']:.0f}/s)")
    print(f"forwarder adds {result['forwarder_added_p50_ms']:.3f} ms p50; goal "
          f"<= {GOAL_ADDED_P50_MS} ms and >= {GOAL_THROUGHPUT_FPS:.0f} frames/s: "
          f"{'met' if result['goal']['met'] else 'MISSED'}")
    return 0
