"""Bus fixtures: an isolated bus per test (its own FV_BUS under a short /tmp folder and a
forwarder in a thread), helpers that start `fv` subprocesses in their own process
groups and always kill them, a reader for the nodes' `NodeStatus`, and `wait_for`, the one poll of a
condition until a deadline."""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from contextlib import contextmanager
from typing import Callable, Iterator

import pytest

from msgs import NodeStatus
from nodes.bus import TopicReader
from nodes.endpoints import BUS_ENV, BusAddress, bus_address
from nodes.forwarder import Forwarder
from nodes.node import Node

REPO = Path(__file__).resolve().parents[2]


class Bus:
    """One test's bus: its address, its folder, and the forwarder serving it."""

    def __init__(self, folder: Path, address: BusAddress) -> None:
        self.folder = folder
        self.address = address
        self.forwarder: Forwarder | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start_forwarder(self, **kwargs: object) -> Forwarder:
        """Serve this bus from a thread of the test process (kwargs: Forwarder's tcp_url, keys);
        again after stop_forwarder() to restart it."""
        self._stop = threading.Event()
        self.forwarder = Forwarder(self.address, **kwargs)
        self._thread = threading.Thread(target=self.forwarder.run, args=(self._stop,), daemon=True)
        self._thread.start()
        return self.forwarder

    def stop_forwarder(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(2.0)
            self.forwarder.close()
            self._thread = None


@pytest.fixture
def bus_env(monkeypatch: pytest.MonkeyPatch) -> Iterator[Bus]:
    """An isolated bus address (FV_BUS set for this test and its subprocesses), no forwarder."""
    folder = Path(tempfile.mkdtemp(prefix="fvt", dir="/tmp"))  # IPC paths must stay short (< 107 bytes)
    address = bus_address(f"ipc://{folder}/bus")
    monkeypatch.setenv(BUS_ENV, address.url)
    bus = Bus(folder, address)
    yield bus
    bus.stop_forwarder()
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def bus(bus_env: Bus) -> Bus:
    """An isolated bus with a forwarder running in a thread."""
    bus_env.start_forwarder()
    return bus_env


def kill_group(proc: subprocess.Popen, grace_s: float = 1.0) -> None:
    """SIGTERM the process group `proc` leads, SIGKILL it after `grace_s`; reap `proc`."""
    for sig, wait_s in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            pass
        try:
            proc.wait(wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


# The launches whose states are compared frame by frame (with `fv eval`, or a replay with the live run) play
# videos at half their 25 fps: each node keeps only its latest frame, so a tracker that fell behind on a loaded
# 2-core machine drops a frame, and every later P(slip) of the grasp differs. At a rate slower than the
# model's, every frame is judged as offline.
EVERY_FRAME_FPS = 12.5


def hangup_as_from_a_terminal() -> None:
    """`preexec_fn` of a spawned `fv`: SIGHUP at its default, as a process started from a terminal has it. Tests
    run under `nohup` would leave it ignored in every child, which then (as `nohup` asks) runs on after a
    hangup, and a test of the stop on SIGHUP would fail."""
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


@pytest.fixture
def spawn(bus_env: Bus) -> Iterator[Callable[..., subprocess.Popen]]:
    """spawn(*fv_args, stdout=PIPE...) -> Popen of `python -m nodes.cli *fv_args` on the
    test's bus, in its own process group; every one is killed at teardown."""
    procs: list[subprocess.Popen] = []

    def start(*args: str, **kwargs: object) -> subprocess.Popen:
        kwargs.setdefault("stdout", subprocess.DEVNULL)
        kwargs.setdefault("stderr", subprocess.DEVNULL)
        kwargs.setdefault("preexec_fn", hangup_as_from_a_terminal)
        proc = subprocess.Popen([sys.executable, "-m", "nodes.cli", *args], cwd=REPO, start_new_session=True,
                                env=dict(os.environ, PYTHONUNBUFFERED="1"), **kwargs)
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        kill_group(proc)


@contextmanager
def spinning(node: Node) -> Iterator[Node]:
    """Run `node` in a thread of the test process; stop it at the end."""
    thread = threading.Thread(target=node.spin, kwargs={"install_signals": False}, daemon=True)
    thread.start()
    try:
        yield node
    finally:
        node.stop()
        thread.join(5.0)
        assert not thread.is_alive(), f"node {node.name} did not stop"


def run_fv(*args: str, timeout_s: float = 10.0) -> subprocess.CompletedProcess:
    """Run `fv *args` to completion on the current FV_BUS; output as text."""
    return subprocess.run([sys.executable, "-m", "nodes.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout_s)


def poll_until(predicate: Callable[[], object], timeout_s: float, period_s: float = 0.01,
               between: Callable[[], object] | None = None) -> bool:
    """Call `predicate` every `period_s` until it returns a true value (True) or `timeout_s` has passed without
    (False: the caller asserts what it expected, with what it saw). After each false answer `between` is called,
    if given (a message published until it is heard)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() >= deadline:
            return False
        if between is not None:
            between()
        time.sleep(period_s)
    return True


def wait_for(predicate: Callable[[], object], timeout_s: float, what: str, period_s: float = 0.01,
             between: Callable[[], object] | None = None) -> float:
    """`poll_until` that must succeed: the seconds it took; AssertionError "`what`: not within `timeout_s` s"
    when `timeout_s` has passed without."""
    t0 = time.monotonic()
    assert poll_until(predicate, timeout_s, period_s, between), f"{what}: not within {timeout_s} s"
    return time.monotonic() - t0


def wait_status(node: str, predicate: Callable[[NodeStatus], bool] = lambda st: True,
                timeout_s: float = 5.0) -> NodeStatus:
    """The first NodeStatus of `node` that satisfies `predicate`; AssertionError with the
    last one seen after `timeout_s`."""
    last = None
    deadline = time.monotonic() + timeout_s
    with TopicReader(["/status"]) as reader:
        while (remaining := deadline - time.monotonic()) > 0:
            item = reader.recv(remaining)
            if item is not None and item.msg.node == node:
                last = item.msg
                if predicate(last):
                    return last
    raise AssertionError(f"no matching NodeStatus from {node!r} within {timeout_s} s; last: {last}")


def children_of(pid: int) -> list[int]:
    """Pids whose parent is `pid` (from /proc/*/stat)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    fields = f.read().rpartition(")")[2].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                out.append(int(entry))
    return out
