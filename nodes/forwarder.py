"""The forwarder: one per host, like roscore. XSUB (publishers) <-> XPUB (subscribers).

It forwards every message, caches the last latched message per (topic, node) and
replays it to each new subscriber while its publisher is connected (`nodes.latched_cache`: a gone
publisher's only to subscribers that ask for those), and answers pings on the control socket. Locally it
binds IPC only; with `tcp` it also listens for other hosts, and then only with CURVE
encryption and authenticated client keys.

A forwarder may be restarted while nodes run (the launcher restarts the one it started):
nodes reconnect by themselves, and each publisher re-sends its latched messages to fill
the new forwarder's cache (`nodes.bus.PublisherSocket`).
"""
from __future__ import annotations

import fcntl
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import zmq
from zmq.auth.thread import ThreadAuthenticator
from zmq.utils.monitor import recv_monitor_message

from nodes.bus import LATCHED, LINGER_MS, connect_client, new_context
from nodes.endpoints import BUS_ENV, BusAddress, bus_address, secure_server
from nodes.exit_codes import CONFIG, OK, on_stop_signals
from nodes.latched_cache import LatchedCache
from nodes.parent_death import parent_env
from nodes.proc_stats import process_state
from nodes.process_stop import stop_process

log = logging.getLogger("fv.forwarder")
FWD_HWM = 200
ANSWER_WAIT_S = 2.0  # how long a ping waits for a forwarder's answer by default, and at least over TCP
AUTHORIZED_CHECK_S = 1.0  # how often a TCP forwarder looks for changed client keys in authorized/
START_TIMEOUT_S = 30.0  # how long a started forwarder process may take to answer (its Python start, loaded host)


class ForwarderRunning(RuntimeError):
    """Another forwarder already serves this bus."""


def lock_path(address: BusAddress) -> Path:
    """The file an IPC bus's forwarder holds locked while it runs, its pid written in it."""
    return Path(address.url[len("ipc://"):] + ".lock")


def lock_holder(address: BusAddress) -> int | None:
    """The pid written in the lock file of `address` (an IPC bus) by the forwarder that holds it; None when
    the file is absent or holds no pid (one written by a forwarder before pids were written in it)."""
    if address.ipc_dir is None:
        return None
    try:
        text = lock_path(address).read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def silent_forwarder(address: BusAddress) -> str:
    """For a bus whose forwarder did not answer a ping: the forwarder process that holds it and what to do
    (`forwarder pid 4242 holds the bus but is stopped (as by Ctrl-Z in its terminal): continue it ...`, or `...
    does not answer (hung?) ...`); "" when the bus's lock file names no live forwarder process (none runs, or one
    killed by SIGKILL left its pid there). A forwarder stopped by Ctrl-Z in its terminal, or hung, held the bus,
    and launches and tools said only that none answered."""
    pid = lock_holder(address)
    try:
        if pid is None or b"forwarder" not in Path(f"/proc/{pid}/cmdline").read_bytes():
            return ""
    except OSError:
        return ""
    if process_state(pid) == "T":
        return (f"forwarder pid {pid} holds the bus but is stopped (as by Ctrl-Z in its terminal): continue it "
                f"(kill -CONT {pid}) or end it, or use another FV_BUS")
    return f"forwarder pid {pid} holds the bus but does not answer (hung?): end it, or use another FV_BUS"


class Forwarder:
    """Bind the bus endpoints (IPC, plus TCP+CURVE when `tcp_url` is given)."""

    def __init__(self, address: BusAddress | None = None, tcp_url: str | None = None,
                 keys: Path | None = None) -> None:
        self.address = address or bus_address()
        self.ctx = zmq.Context()
        self._lock_file = None
        if self.address.ipc_dir is not None:
            self.address.ipc_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
            self._lock_file = open(lock_path(self.address), "a+")  # not emptied before it is locked: its pid
            try:
                fcntl.flock(self._lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                self._lock_file.close()
                holder = lock_holder(self.address)
                raise ForwarderRunning(f"a forwarder{'' if holder is None else f' (pid {holder})'} already serves "
                                       f"{self.address.url}") from None
            self._lock_file.truncate(0)
            self._lock_file.write(f"{os.getpid()}\n")
            self._lock_file.flush()
        self.auth: ThreadAuthenticator | None = None
        self.authorized: Path | None = None  # the client keys' folder of a TCP bus
        self._authorized_seen: list[tuple[str, int]] | None = None  # its key files (name, mtime) when last loaded
        self.sides: list[tuple[zmq.Socket, zmq.Socket, zmq.Socket]] = []
        self.monitors: list[zmq.Socket] = []  # each side's publisher connections closing (EVENT_DISCONNECTED)
        try:
            if self.address.is_tcp:
                self.sides.append(self._bind_side(self.address, keys))
            else:
                self.sides.append(self._bind_side(self.address, None))
            if tcp_url:
                self.sides.append(self._bind_side(bus_address(tcp_url), keys))
        except BaseException:
            self.close()
            raise
        self.latched = LatchedCache()
        self.forwarded = 0
        self.started = time.time()

    def _bind_side(self, address: BusAddress, keys: Path | None) -> tuple[zmq.Socket, zmq.Socket, zmq.Socket]:
        secure = address.is_tcp
        if secure:
            if keys is None:
                raise ValueError(f"TCP bus {address.url} needs CURVE keys (--keys DIR, made by `fv keys DIR`)")
            if self.auth is None:
                self.auth = ThreadAuthenticator(self.ctx)
                self.auth.start()
                self.authorized = keys / "authorized"
                self.reload_authorized()
        xsub = self.ctx.socket(zmq.XSUB)
        xpub = self.ctx.socket(zmq.XPUB)
        ctl = self.ctx.socket(zmq.REP)
        xpub.setsockopt(zmq.XPUB_VERBOSER, 1)
        xpub.sndhwm = FWD_HWM
        xsub.rcvhwm = FWD_HWM
        xsub.sndhwm = 0  # subscriptions only: one that finds the queue full is dropped (`bus.subscriber_socket`)
        for sock, endpoint in ((xsub, address.pub), (xpub, address.sub), (ctl, address.ctl)):
            sock.linger = LINGER_MS
            if secure:
                secure_server(sock, keys)
            try:
                sock.bind(endpoint)
            except zmq.ZMQError as exc:  # a port another program holds: a line, not a traceback
                for made in (xsub, xpub, ctl):
                    made.close(linger=0)
                raise ValueError(f"cannot listen on {endpoint}: {exc.strerror}") from None
        xsub.send(b"\x01" + LATCHED)
        self.monitors.append(xsub.get_monitor_socket(zmq.EVENT_DISCONNECTED))
        return xsub, xpub, ctl

    def reload_authorized(self) -> None:
        """(Re)load the client keys of `authorized/` when its key files changed since they were last
        loaded: a key copied in while the forwarder runs is taken within a second (it was taken only
        after a restart, though the refused client is told to copy its key there)."""
        if self.auth is None or self.authorized is None:
            return
        try:
            seen = sorted((f.name, f.stat().st_mtime_ns) for f in self.authorized.iterdir() if f.is_file())
        except OSError:
            seen = []
        if seen == self._authorized_seen:
            return
        self.auth.configure_curve(domain="*", location=str(self.authorized))
        if self._authorized_seen is not None:
            log.info("authorized client keys reloaded from %s: %d file(s)", self.authorized, len(seen))
        self._authorized_seen = seen

    def info(self) -> dict:
        return {"pid": os.getpid(), "url": self.address.url, "uptime_s": time.time() - self.started,
                "forwarded": self.forwarded, "latched": _names(self.latched.live), "gone": _names(self.latched.gone)}

    def run(self, stop: threading.Event) -> None:
        poller = zmq.Poller()
        for sock in [sock for side in self.sides for sock in side] + self.monitors:
            poller.register(sock, zmq.POLLIN)
        xsubs = [s[0] for s in self.sides]
        xpubs = [s[1] for s in self.sides]
        ctls = [s[2] for s in self.sides]
        keys_checked = time.monotonic()
        while not stop.is_set():
            if time.monotonic() - keys_checked >= AUTHORIZED_CHECK_S:
                self.reload_authorized()
                keys_checked = time.monotonic()
            self._ask_publishers(xsubs, self.latched.expire(time.monotonic()))
            for sock, _ in poller.poll(100):
                if sock in xsubs:
                    self._forward(sock, xpubs)
                elif sock in xpubs:
                    event = sock.recv()
                    for up in xsubs:
                        up.send(event)
                    if event[:1] == b"\x01":
                        for frames in list(self.latched.replay(event[1:])):
                            sock.send_multipart(frames, copy=False, flags=zmq.NOBLOCK)
                elif sock in self.monitors:
                    recv_monitor_message(sock)
                    for up in xsubs:  # what the gone publisher sent before it left is no answer to the refresh
                        while up.poll(0):
                            self._forward(up, xpubs)
                    self._ask_publishers(xsubs, self.latched.publisher_left(time.monotonic()))
                elif sock in ctls:
                    sock.recv_multipart()  # every frame: a REP answers only a whole request (a 2-frame one ended it)
                    sock.send(msgpack.packb(self.info()))

    def _forward(self, xsub: zmq.Socket, xpubs: list[zmq.Socket]) -> None:
        """Forward one message from the publishers' side `xsub` to every subscribers' side, keeping a latched
        one (a publisher's answer to a refresh, which subscribers have had, is not forwarded again)."""
        frames = xsub.recv_multipart(copy=False)
        if frames[0].bytes[:1] == LATCHED and not self.latched.received(frames):
            return
        for out in xpubs:
            out.send_multipart(frames, copy=False, flags=zmq.NOBLOCK)
        self.forwarded += 1

    @staticmethod
    def _ask_publishers(xsubs: list[zmq.Socket], events: list[bytes]) -> None:
        """Send subscription events (a refresh made or ended) to every publisher."""
        for event in events:
            for up in xsubs:
                up.send(event)

    def close(self) -> None:
        """Close the sockets, and remove the IPC socket files this forwarder made (the lock held), which one
        killed with SIGKILL leaves: `ping` tells those from a serving forwarder's by a refused connect, and the
        next forwarder's bind replaces them."""
        for (xsub, _, _), monitor in zip(self.sides, self.monitors):
            xsub.disable_monitor()
            monitor.close(linger=0)
        for side in self.sides:
            for sock in side:
                sock.close(linger=0)
        if self.auth is not None:
            self.auth.stop()
        self.ctx.term()
        if self._lock_file is not None:
            if self.sides:  # its IPC side was bound (the first)
                for path in self.address.ipc_files:
                    path.unlink(missing_ok=True)
                self._lock_file.truncate(0)  # its pid: no other forwarder's, read while that one writes its own
            self._lock_file.close()


def _names(messages: dict[bytes, list]) -> list[str]:
    """The envelopes of cached messages as text (flag, topic, NUL, publisher node), sorted."""
    return sorted(env.decode(errors="replace") for env in messages)


def _nobody_listens(path: Path) -> bool:
    """True when no process listens on the IPC socket file `path`: it is absent, or a connect to it is refused
    (the file a killed forwarder left). A forwarder that listens sees a peer that leaves before its handshake."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.setblocking(False)  # a listener whose backlog is full: BlockingIOError, not a wait
        try:
            probe.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError):
            return True
        except OSError:  # not ours to judge (e.g. no permission): the ping says
            return False
    return False


def ping(address: BusAddress | None = None, timeout_s: float = ANSWER_WAIT_S) -> dict | None:
    """The forwarder's info, or None when no forwarder answers within `timeout_s` (on TCP at least
    `ANSWER_WAIT_S`: the CURVE handshake comes first); at once when nothing listens on the bus's IPC control
    socket file (absent, or left by a forwarder killed with SIGKILL: each ping waited its whole `timeout_s`
    for an answer that could not come). On a loaded 2-core host 0.3 s missed a forwarder that was serving
    (`fv topic hz` over TCP 2 times in 16, `fv topic echo` over IPC 1 in 16: "no launch runs on this bus");
    a shorter `timeout_s` is a quick look."""
    address = address or bus_address()
    if address.is_tcp:
        timeout_s = max(timeout_s, ANSWER_WAIT_S)
    elif _nobody_listens(address.ipc_files[-1]):  # the ctl socket file
        return None
    ctx = new_context()
    sock = ctx.socket(zmq.REQ)
    sock.linger = 0
    try:
        connect_client(sock, address, address.ctl)  # on TCP a refused CURVE handshake is logged, not silent
        sock.send(b"ping")
        if sock.poll(int(timeout_s * 1000)):
            return msgpack.unpackb(sock.recv())
        return None
    finally:
        sock.close(linger=0)


class ForwarderStart:
    """A forwarder process started on `address`, until it answers: `answered()` looks once, without waiting
    for it, so that its caller decides how to wait (`ensure_forwarder` blocks; the launcher looks on each pass
    of its supervise loop and supervises its nodes meanwhile). The process stops when the caller dies
    (`nodes.parent_death`). One that starts is waited for up to `timeout_s`: a Python process's start, 0.6 s
    here, took over 5 s on a loaded host (a test run beside two others), and the launch failed ("did not
    answer within 5.0 s")."""

    def __init__(self, address: BusAddress, timeout_s: float = START_TIMEOUT_S) -> None:
        env = dict(os.environ, **{BUS_ENV: address.url}, **parent_env())
        self.address = address
        self.timeout_s = timeout_s
        self.proc = subprocess.Popen([sys.executable, "-m", "nodes.cli", "forwarder"], env=env,
                                     start_new_session=False)
        self._deadline = time.monotonic() + timeout_s

    def answered(self) -> bool:
        """True once the forwarder answers a ping (of up to 0.2 s; at once while nothing listens on its socket
        file), False while it may still. ForwarderRunning when another forwarder answers (its pid is not this
        process's: it took the bus as this one started, e.g. another launch's), this one then stopped; it was
        taken for this one, which had exited. RuntimeError when this one exited at its start (its code said, and
        for a bus held by a forwarder that does not answer, which), or when `timeout_s` passed without an answer:
        then it is stopped (`stop`)."""
        info = ping(self.address, 0.2)
        if info is None and self.proc.poll() == CONFIG:
            info = ping(self.address)  # the bus was taken: by a forwarder still starting, or one that is stuck
        if info is not None:
            if info.get("pid") == self.proc.pid:
                return True
            self.stop()
            raise ForwarderRunning(f"another forwarder (pid {info.get('pid')}) serves {self.address.url}")
        if self.proc.poll() is not None:
            holder = silent_forwarder(self.address) if self.proc.returncode == CONFIG else ""
            raise RuntimeError(f"forwarder for {self.address.url} exited with code {self.proc.returncode} at start"
                               + (f": {holder}" if holder else ""))
        if time.monotonic() >= self._deadline:
            self.stop()
            raise RuntimeError(f"forwarder for {self.address.url} did not answer within {self.timeout_s} s")
        return False

    def stop(self) -> None:
        """Stop the process no longer waited for (SIGTERM, SIGKILL after 5 s) and reap it: it was left a
        zombie until the launch exited."""
        stop_process(self.proc, signal.SIGTERM, 5.0)


def ensure_forwarder(address: BusAddress | None = None, timeout_s: float = START_TIMEOUT_S,
                     stop: threading.Event | None = None) -> subprocess.Popen | None:
    """Start a forwarder process unless one answers and wait for its answer (`ForwarderStart`, up to
    `timeout_s`); returns it (the caller stops it) or None when one was already running, or took the bus as
    this one started. Once `stop` is set, none is started and the one started is no longer waited for (it is
    stopped): RuntimeError, as when it cannot start. A launch stopped as it looked for a forwarder started one, waited for its answer, then
    stopped it: 0.5 to 0.7 s before its stop began. A forwarder that listens on the bus is waited for as long
    as `ping` waits (a killed one's socket file is told at once): a quick look of 0.3 s missed a serving one
    on a loaded host, and the forwarder started then could not take the bus's lock ("exited with code 2 at
    start")."""
    address = address or bus_address()
    stop = stop or threading.Event()
    if ping(address) is not None:
        return None
    if stop.is_set():
        raise RuntimeError(f"stopped before a forwarder for {address.url} was started")
    start = ForwarderStart(address, timeout_s)
    try:
        while not start.answered():
            if stop.wait(0.05):
                start.stop()
                raise RuntimeError(f"stopped before the forwarder for {address.url} answered")
    except ForwarderRunning:  # another forwarder took the bus as this one started: it serves
        return None
    return start.proc


def serve(tcp_url: str | None = None, keys: Path | None = None) -> int:
    """Run a forwarder in this process until one of `stop_signals()`; the `fv forwarder` command. Another
    forwarder serving the bus raises ForwarderRunning, which the command line says and exits CONFIG with (as a
    second `fv launch` of the same nodes on one bus: the setup, not this process, is wrong)."""
    fwd = Forwarder(tcp_url=tcp_url, keys=keys)
    stop = threading.Event()
    on_stop_signals(lambda _signum: stop.set())
    log.info("forwarder on %s%s", fwd.address.url, f" and {tcp_url} (CURVE)" if tcp_url else "")
    try:
        fwd.run(stop)
    finally:
        fwd.close()
    return OK
