"""Run a launch file: start the forwarder when none runs, one process per node, prefix
their output with the node name, respawn what should respawn, and stop everything on
Ctrl-C, SIGTERM, SIGHUP (its terminal closed), the exit of a required node or a node that
cannot start (`fv launch FILE [name:=value ...]`).

Each node runs in its own process group, so a terminal's Ctrl-C reaches only the
launcher, which then stops the nodes in order: SIGTERM to each group, SIGKILL after
`GRACE_S`, then the forwarder it started. A launcher killed outright (SIGKILL) cannot: its
nodes, spares and forwarder get SIGTERM from the kernel when it dies (`nodes.parent_death`), so
they must be started from the main thread or the supervisor, which live as long as the launch.

The launcher supervises the forwarder it started (restarted when it dies; nodes
reconnect by themselves and re-send their latched messages). A launch that found another's
forwarder running on its IPC bus pings it every `FORWARDER_CHECK_S` and starts its own when it is
gone (the other launch stopped): its nodes would otherwise wait for a forwarder for good. A forwarder
(re)started while the nodes run is looked at on each pass of the supervise loop until it answers, so the
nodes are supervised meanwhile (only the launch's first forwarder is waited for before any node starts).
It publishes its own `NodeStatus` on `/status` as `launch_<file stem>`: counters `respawns`,
`<node>.respawns`, `forwarder_restarts`, `running`, `waiting`, and state "error" naming a node
whose process is stopped (SIGSTOP), whose NodeStatus has been missing for `SILENT_AFTER_S` or that
cannot start, "warn" for a node waiting to respawn, waiting for what it needs, or gone with an error code.

A respawning node is started again by its exit code (`nodes.exit_codes`). TEMPFAIL (what it needs
is not there yet: a camera not plugged in): every `respawn_delay` until it is up (within
`max_retries`), said once, its repeated output not echoed. CONFIG before its first NodeStatus (a
configuration error at its start): `START_TRIES` starts in a row at most, then the launch stops with
CONFIG, as it does at once for a node without respawn, whatever `required` says: the launch as
configured cannot run. CONFIG_WHILE_RUNNING (a configuration error a running node found): the launch
stops at once, with CONFIG. Any other exit: as `respawn` and `max_retries` say.

A node with `standby: true` also gets a spare process (`fv node KIND --standby`) that has
done its imports and waits; when the node exits, the spare takes over at once (SIGUSR1)
and a new spare is started after `respawn_delay`. Without a ready spare the node is
respawned as usual.
"""
from __future__ import annotations

import argparse
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from msgs.param import ParamState
from nodes import launch_checks
from nodes.endpoints import BusAddress
from nodes.exit_codes import CONFIG, CONFIG_WHILE_RUNNING, FAILED, OK, TEMPFAIL, on_stop_signals
from nodes.launch_file import NodeSpec, load_launch, parse_arg_overrides
from nodes.node import LAUNCH_ENV, STANDBY_READY
from nodes.param_service import param_topics, set_params
from nodes.parent_death import parent_env
from nodes.proc_stats import process_alive, process_state

if TYPE_CHECKING:
    from nodes.forwarder import ForwarderStart

GRACE_S = 1.2
NAMESAKE_WAIT_S = 0.5  # how long a launch on a running bus listens for the NodeStatus of namesakes
FORWARDER_GRACE_S = 0.5
FORWARDER_RETRY_S = 1.0  # wait between failed forwarder restarts
FORWARDER_CHECK_S = 1.0  # period of the pings to a forwarder this launch shares (did not start)
SPARE_RETRY_S = 1.0  # at least this long before replacing a spare that died (a spare that cannot start loops slowly)
SPARE_RETRY_MAX_S = 60.0  # the longest wait, doubled from SPARE_RETRY_S for each spare in a row that never got ready
POLL_S = 0.05
READY_POLL_S = 0.01  # how often a stop looks whether a process still starting takes SIGTERM
TERM_WAIT_S = 0.3  # of GRACE_S, left to a process sent SIGTERM without its handler yet, before it is killed
STATUS_PERIOD_S = 1.0  # the launcher's own NodeStatus period
SILENT_AFTER_S = 3.0  # a running node whose NodeStatus stopped this long is reported (nodes send one per second)
PARAMS_AGAIN_TIMEOUT_S = 10.0  # how long a restarted node has to take the params set live before it (s)
START_TRIES = 3  # starts in a row that end in a configuration error before the launch stops (a file still being
# written may pass the next time; a bad param never does)
LINES_KEPT = 20  # a process's last output lines kept: its error, the lines a waiting node does not repeat
STATUS_TOPIC = "/status"

_log = logging.getLogger("launch")


@dataclass
class Child:
    """A node's current process and its supervision state.

    retries: respawns so far. exit_code: the last exit's code. error: the last line its last
    process said (its error), lines: the last `LINES_KEPT` lines of the current process's output.
    last_status_s: monotonic time of the current process's last NodeStatus (None before its first).
    fault: the kind of problem last said for it ("stopped", "silent" or ""), so each is said once.
    start_failures: exits with CONFIG before a NodeStatus, in a row. cannot_run: it ends the
    launch: START_TRIES of them (or no respawn left), or an exit CONFIG_WHILE_RUNNING. waiting_since: monotonic time of the first of its
    exits with TEMPFAIL in a row (None when the last exit was another), quiet: the lines those
    tries printed (`_numbers_masked`), not echoed again. spare: the standby process (standby
    nodes), spare_ready: it said STANDBY_READY, spare_lines: its output lines, spare_at: when to
    start the next spare, spare_failures: spares in a row that exited before they were ready.
    start_params, live_params, params_due: the params set live (`fv param set`), given again to each process
    that takes the node's place (`Launch._read_param_states`).
    """

    spec: NodeSpec
    proc: subprocess.Popen | None = None
    retries: int = 0
    restart_at: float | None = None
    reader: threading.Thread | None = None
    exit_code: int | None = None
    error: str = ""
    lines: list[str] = field(default_factory=list)
    last_status_s: float | None = None
    fault: str = ""
    start_failures: int = 0
    cannot_run: bool = False
    waiting_since: float | None = None
    quiet: set[str] = field(default_factory=set)
    spare: subprocess.Popen | None = None
    spare_reader: threading.Thread | None = None
    spare_ready: bool = False
    spare_lines: list[str] = field(default_factory=list)
    spare_at: float | None = None
    spare_failures: int = 0
    start_params: dict[str, Any] | None = None  # the params its first process started with (its ParamState)
    live_params: dict[str, Any] = field(default_factory=dict)  # set live since (`fv param set`), kept over restarts
    params_due: bool = False  # the current process has not been given `live_params` yet


class Launch:
    """A validated set of nodes and the processes running them.

    >>> launch = Launch.from_file("launch/demo.yaml", {"rate_hz": 5})
    >>> launch.start(); ...; launch.stop()
    """

    def __init__(self, specs: list[NodeSpec], output: TextIO | None = None, name: str = "launch") -> None:
        """specs: the validated nodes; output: where prefixed node output goes (default
        stdout); name: the node name of the launcher's own NodeStatus."""
        self.specs = specs
        self.output = output or sys.stdout
        self.name = name
        self.children = [Child(spec) for spec in specs]
        self.exit_code = 0
        self.forwarder_restarts = 0
        self._forwarder: subprocess.Popen | None = None
        self._forwarder_retry_at: float | None = None  # when to (re)try starting the forwarder; None = not needed
        self._forwarder_start: ForwarderStart | None = None  # a forwarder (re)started, not answering yet
        self._forwarder_check_at = 0.0  # next ping of a shared forwarder
        self._silent_forwarder = ""  # why the bus's forwarder runs but does not answer ("" while it answers)
        self._bus_back_s = 0.0  # when a (re)started forwarder last answered (monotonic s): nodes were silent before
        self._address = None
        self._status_pub = None
        self._status_reader = None
        self._param_reader = None  # the nodes' ParamState topics
        self._by_param_topic = {param_topics(c.spec.name)[1]: c for c in self.children}  # their nodes
        self._params = None  # NoParamService: `fv param` answered for launch_<stem>
        self._started = time.monotonic()
        self._started_ns = time.time_ns()  # given to every node (LAUNCH_ENV)
        self._out_lock = threading.Lock()
        self._stop = threading.Event()
        self._done = threading.Event()
        self._supervisor: threading.Thread | None = None

    @classmethod
    def from_file(cls, path: str | Path, args: dict[str, Any] | None = None, output: TextIO | None = None) -> "Launch":
        """Parse and validate `path` with launch arguments `args`; LaunchError names file, line and key."""
        return cls(load_launch(path, args), output, name=f"launch_{Path(path).stem}")

    # -- output ----------------------------------------------------------------------
    def say(self, text: str, who: str = "launch") -> None:
        """Write one line prefixed by `[who]` (whole lines, never interleaved); dropped when the
        output is gone (a closed terminal: EIO), so the nodes' output is still drained and the
        launch still stops them."""
        prefix = f"[{who}] "
        line = text if text.startswith(prefix) else prefix + text
        with self._out_lock:
            try:
                self.output.write(line.rstrip("\n") + "\n")
                self.output.flush()
            except OSError:
                pass

    def _pump(self, child: Child, stream: TextIO, lines: list[str], spare: bool = False) -> None:
        """Echo the output of `child`'s process (or its spare's), keeping its last LINES_KEPT lines in
        `lines`: a spare's STANDBY_READY line is noted, not echoed, and while the node waits (exit
        TEMPFAIL) the lines its earlier tries printed (but for their numbers) are not echoed again."""
        for line in stream:  # node log lines already start with "[name] ": say() keeps one prefix
            if spare and line.strip() == STANDBY_READY:
                child.spare_ready = True
                continue
            text = line.rstrip("\n")
            lines.append(text)
            del lines[:-LINES_KEPT]
            if child.waiting_since is None or _numbers_masked(text) not in child.quiet:
                self.say(text, child.spec.name)
        stream.close()

    # -- processes -------------------------------------------------------------------
    def _popen(self, spec: NodeSpec, *extra: str) -> subprocess.Popen:
        env = {**os.environ, "PYTHONUNBUFFERED": "1", LAUNCH_ENV: str(self._started_ns), **parent_env(),
               **launch_checks.env(), **spec.env}  # launch_checks: the checks made as it loaded
        return subprocess.Popen([sys.executable, "-m", "nodes.cli", *spec.argv(), *extra], env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, bufsize=1, start_new_session=True)

    def _spawn(self, child: Child) -> None:
        spec = child.spec
        child.proc = self._popen(spec)
        child.restart_at = None
        child.last_status_s = None
        child.lines = []
        child.reader = threading.Thread(target=self._pump, args=(child, child.proc.stdout, child.lines),
                                        name=f"out-{spec.name}", daemon=True)
        child.reader.start()
        child.params_due = bool(child.live_params)
        if child.waiting_since is None:  # a waiting node's tries are said once, when it starts waiting
            self.say(f"started {spec.name} ({spec.kind}) pid {child.proc.pid}")
        if spec.standby and child.spare is None:
            child.spare_at = time.monotonic()

    def _spawn_spare(self, child: Child) -> None:
        spec = child.spec
        child.spare_ready = False
        child.spare_at = None
        child.spare = self._popen(spec, "--standby")
        child.spare_lines = []
        child.spare_reader = threading.Thread(target=self._pump, name=f"out-{spec.name}-spare", daemon=True,
                                              args=(child, child.spare.stdout, child.spare_lines, True))
        child.spare_reader.start()
        self.say(f"started a spare {spec.name} pid {child.spare.pid}")

    def _watch_spare(self, child: Child, now: float) -> None:
        """Start a standby node's next spare when due; notice a spare that died."""
        if child.spare is not None and child.spare.poll() is not None:
            child.spare_failures = 0 if child.spare_ready else child.spare_failures + 1
            wait_s = min(SPARE_RETRY_MAX_S, max(child.spec.respawn_delay_s, SPARE_RETRY_S)
                         * 2 ** max(child.spare_failures - 1, 0))  # one that cannot start: its error said less often
            self.say(f"spare {child.spec.name} pid {child.spare.pid} exited with code {child.spare.returncode}"
                     + (f" before it was ready ({child.spare_failures} in a row); next spare in {wait_s:g} s"
                        if child.spare_failures else ""))
            _signal_group(child.spare, signal.SIGTERM)
            child.spare = None
            child.spare_at = now + wait_s
        if child.spare is None and child.spare_at is not None and now >= child.spare_at and child.proc is not None:
            self._spawn_spare(child)

    def _promote_spare(self, child: Child, now: float, exited: str) -> bool:
        """Let a ready spare take over the exited node (`exited` says how it exited); False when there is none."""
        spare = child.spare
        if spare is None or not child.spare_ready or spare.poll() is not None:
            return False
        os.kill(spare.pid, signal.SIGUSR1)
        child.proc, child.reader, child.lines = spare, child.spare_reader, child.spare_lines
        child.spare, child.spare_reader, child.spare_ready = None, None, False
        child.last_status_s = None
        child.params_due = bool(child.live_params)
        child.spare_at = now + child.spec.respawn_delay_s
        self.say(f"{exited}; spare pid {spare.pid} took over (respawn {child.retries})")
        return True

    def pid(self, name: str) -> int | None:
        """The pid of node `name`'s running process, None when it is not running."""
        for child in self.children:
            if child.spec.name == name and child.proc is not None and child.proc.poll() is None:
                return child.proc.pid
        return None

    @property
    def forwarder_pid(self) -> int | None:
        """The pid of the forwarder this launch started, None when it uses one already running."""
        return None if self._forwarder is None else self._forwarder.pid

    def start(self) -> None:
        """Start the forwarder (when none answers) and every node; supervise in a thread. Call it from a
        thread that lives as long as the launch: what it starts gets SIGTERM when it ends (`nodes.parent_death`).
        Once the launch is stopped (`run`'s stop signal), the nodes not yet started are not: Ctrl-C as a launch
        started had each node started, to be stopped at once, as its interpreter started (killed by the
        SIGTERM, -15)."""
        from nodes.bus import PublisherSocket, TopicReader
        from nodes.endpoints import bus_address
        from nodes.param_service import NoParamService

        self._address = address = bus_address()
        if not self._stop.is_set():
            self._start_forwarder(address)
        self._status_pub = PublisherSocket(self.name, address)
        self._status_reader = TopicReader([STATUS_TOPIC], address)
        self._param_reader = TopicReader(list(self._by_param_topic), address)
        self._params = NoParamService(self.name, self._status_pub, address)
        try:
            for child in self.children:
                if self._stop.is_set():
                    break
                self._spawn(child)
        except BaseException:
            self._shutdown()
            raise
        self._supervisor = threading.Thread(target=self._supervise, name="launch-supervisor", daemon=True)
        self._supervisor.start()

    def _start_forwarder(self, address: BusAddress) -> None:
        """Start a forwarder on `address` when none answers, unless it is a TCP bus, whose forwarder must run
        already. RuntimeError when none serves it, or when this launch's nodes run on it already; not once the
        launch is stopped (`ensure_forwarder`'s `stop`): a forwarder stopped with it as it started (Ctrl-C reaches
        both) made the launch say "forwarder ... exited with code 130 at start" and exit 2."""
        from nodes.forwarder import ensure_forwarder, ping

        if address.is_tcp:
            if ping(address) is None:  # (over TCP a ping waits at least ANSWER_WAIT_S)
                raise RuntimeError(f"no forwarder answers at {address.url}; start `fv forwarder --tcp ...` there")
        else:
            try:
                self._forwarder = ensure_forwarder(address, stop=self._stop)
            except RuntimeError:
                if self._stop.is_set():
                    return
                raise
            if self._forwarder is not None:
                self.say(f"started forwarder on {address.url} pid {self._forwarder.pid}")
        if self._forwarder is None:  # a forwarder serves this bus already: another launch may be on it
            running = self._namesakes_running()
            if running:
                raise RuntimeError(f"nodes named {', '.join(running)} already run on {address.url} (another launch?): "
                                   "two pipelines on one bus mix their topics; stop that launch, or give this one "
                                   "another FV_BUS or a namespace")

    def _namesakes_running(self) -> list[str]:
        """The names of this launch's nodes that a running node on the bus has already: its NodeStatus
        is fresh and, on a local (IPC) bus, its process is alive."""
        from nodes.topic_tools import discover

        alive = discover(NAMESAKE_WAIT_S)
        local = not self._address.is_tcp
        return sorted(child.spec.name for child in self.children if child.spec.name in alive
                      and (not local or process_alive(alive[child.spec.name].pid)))

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until the launch ended by itself (required node died, all nodes exited)
        or was stopped; False on timeout."""
        return self._done.wait(timeout_s)

    def stop(self) -> int:
        """Stop every node and the forwarder this launch started; returns the exit code."""
        self._stop.set()
        if self._supervisor is not None:
            self._supervisor.join()
        return self.exit_code

    def run(self) -> int:
        """start(), then wait for one of `stop_signals()` (Ctrl-C, SIGTERM, SIGHUP unless nohup ignores it)
        or the end of the launch, then stop()."""
        if threading.current_thread() is threading.main_thread():
            on_stop_signals(lambda _signum: self._stop.set())
        try:
            self.start()
            while not self._done.wait(0.1):
                pass
        finally:
            self.stop()
        return self.exit_code

    # -- supervision -----------------------------------------------------------------
    def _supervise(self) -> None:
        next_status_s = time.monotonic()
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                self._watch_forwarder(now)
                self._read_param_states()
                self._read_statuses(now)  # before the exits: a node that reported has started
                for child in self.children:
                    if child.proc is not None and child.proc.poll() is not None:
                        self._exited(child, now)
                    if child.restart_at is not None and now >= child.restart_at and not self._stop.is_set():
                        self._spawn(child)
                    if child.spec.standby and not self._stop.is_set():
                        self._watch_spare(child, now)
                if not any(c.proc is not None or c.restart_at is not None for c in self.children):
                    self.say("all nodes have exited")
                    break
                self._status_pub.update()  # answers the forwarder's refreshes of latched messages
                self._params.answer()
                if now >= next_status_s:
                    self._publish_status(now)
                    next_status_s = now + STATUS_PERIOD_S
                self._stop.wait(POLL_S)
        finally:
            self._shutdown()
            self._done.set()

    def _watch_forwarder(self, now: float) -> None:
        """Restart the forwarder this launch started when it has died, start one when the shared
        IPC forwarder no longer answers (retrying every FORWARDER_RETRY_S while it fails to start). The new
        process is not waited for (`_forwarder_answered` looks on each pass): a restart that waited for its
        answer held the supervise loop up to START_TIMEOUT_S (30 s), the nodes that died meanwhile not respawned
        and the launch's status not sent."""
        from nodes.forwarder import ForwarderStart, ping, silent_forwarder

        if self._forwarder_start is not None:
            self._forwarder_answered()
            return
        if self._forwarder is not None and self._forwarder.poll() is not None:
            dead = self._forwarder
            self.say(f"forwarder pid {dead.pid} exited with code {dead.returncode}; restarting it")
            self._forwarder = None
            self._forwarder_retry_at = now
        elif self._forwarder is not None:
            stopped = process_state(self._forwarder.pid) in ("T", "t")
            self._forwarder_silent(f"forwarder pid {self._forwarder.pid} is stopped (SIGSTOP?)" if stopped else "")
        elif (self._forwarder_retry_at is None and not self._address.is_tcp and now >= self._forwarder_check_at):
            self._forwarder_check_at = now + FORWARDER_CHECK_S
            if ping(self._address, 0.5) is not None:  # a busy forwarder answers in well under 0.5 s
                self._forwarder_silent("")
            elif holder := silent_forwarder(self._address):  # one of ours could not take the bus from it
                self._forwarder_silent(holder)
            else:
                self._forwarder_silent("")
                self.say(f"the forwarder this launch shared on {self._address.url} is gone; starting one")
                self._forwarder_retry_at = now
        if self._forwarder_retry_at is None or now < self._forwarder_retry_at or self._stop.is_set():
            return
        if ping(self._address) is not None:
            self._another_forwarder_serves()
            return
        self._forwarder_start = ForwarderStart(self._address)

    def _forwarder_silent(self, why: str) -> None:
        """Note whether the bus's forwarder runs but answers nothing (`why`, said once; "" when it answers, said
        when it did not): stopped by Ctrl-Z or SIGSTOP, or hung. Meanwhile the nodes' silence is the bus's, not
        theirs (`_check_nodes`), and no forwarder is started: it could not take the bus."""
        if why and not self._silent_forwarder:
            self.say(f"the bus's forwarder does not answer: {why}; the nodes cannot talk until it does")
        elif not why and self._silent_forwarder:
            self._bus_back_s = time.monotonic()
            self.say(f"the bus's forwarder answers again on {self._address.url}")
        self._silent_forwarder = why

    def _another_forwarder_serves(self) -> None:
        """The bus is back, served by a forwarder this launch did not start: said, not supervised."""
        self._forwarder_retry_at, self._bus_back_s = None, time.monotonic()
        self.forwarder_restarts += 1
        self.say(f"another forwarder now serves {self._address.url}; this launch does not supervise it")

    def _forwarder_answered(self) -> None:
        """Look once whether the forwarder being (re)started answers: then it is this launch's, said with its
        restart count. One that exited at its start, or did not answer within START_TIMEOUT_S (stopped), is said
        and started again after FORWARDER_RETRY_S, unless the launch is stopping; when another forwarder took the
        bus as it started, that one serves."""
        from nodes.forwarder import ForwarderRunning

        start = self._forwarder_start
        try:
            if not start.answered():
                return
        except ForwarderRunning:
            self._forwarder_start = None
            self._another_forwarder_serves()
            return
        except RuntimeError as exc:
            self._forwarder_start = None
            if not self._stop.is_set():  # the launch is stopping: no forwarder is wanted any more
                self.say(f"forwarder restart failed: {exc}; retrying in {FORWARDER_RETRY_S:g} s")
                self._forwarder_retry_at = time.monotonic() + FORWARDER_RETRY_S
            return
        self._forwarder_start, self._forwarder_retry_at, self._forwarder = None, None, start.proc
        self._bus_back_s = time.monotonic()
        self.forwarder_restarts += 1
        self.say(f"restarted forwarder on {self._address.url} pid {start.proc.pid} "
                 f"(restart {self.forwarder_restarts})")

    def _read_statuses(self, now: float) -> None:
        """Note the NodeStatus messages of the current processes of this launch's nodes; say when a
        node that waited is up."""
        by_name = {c.spec.name: c for c in self.children}
        while (item := self._status_reader.recv(0.0)) is not None:
            child = by_name.get(item.msg.node)
            if child is not None and child.proc is not None and item.msg.pid == child.proc.pid:
                child.last_status_s = now
                if child.params_due:
                    child.params_due = False
                    threading.Thread(target=self._set_live_params, args=(child.spec.name, dict(child.live_params)),
                                     name=f"params-{child.spec.name}", daemon=True).start()
                if child.waiting_since is not None:
                    self.say(f"{child.spec.name} is up (pid {item.msg.pid}) after waiting "
                             f"{now - child.waiting_since:.1f} s")
                    child.waiting_since, child.quiet = None, set()

    def _read_param_states(self) -> None:
        """Keep, per node, the params set live (`fv param set`, `nodes.client.set_param`) that differ from those its
        first process started with: a process that takes its place (respawned, or a spare) starts with the launch
        file's, and is given them again once it reports (`_set_live_params`). A tuned threshold went back to the
        launch file's at a slip detector's respawn, without a word."""
        while (item := self._param_reader.recv(0.0)) is not None:
            child, state = self._by_param_topic.get(item.topic), item.msg
            if child is None or not isinstance(state, ParamState) or not state.accepted:
                continue
            if child.start_params is None and not state.request_id:
                child.start_params = dict(state.params)
            elif state.request_id and child.start_params is not None:
                child.live_params = {k: state.params[k] for k in state.live
                                     if k in state.params and state.params[k] != child.start_params.get(k)}

    def _set_live_params(self, name: str, values: dict[str, Any]) -> None:
        """Give node `name`'s new process the params set live before it (in a thread: it waits for the answer)."""
        shown = ", ".join(f"{k} {v!r}" for k, v in sorted(values.items()))
        try:
            set_params(name, values, PARAMS_AGAIN_TIMEOUT_S, self._address)
        except (ValueError, TimeoutError) as exc:  # ParamError is a ValueError
            self.say(f"{name}: the params set live before its restart ({shown}) were not set again: {exc}; it runs "
                     "with the launch file's")
            return
        self.say(f"{name}: the params set live before its restart set again: {shown}")

    def _check_nodes(self, now: float) -> list[tuple[str, str]]:
        """(state, message) per node in trouble: its process stopped or its NodeStatus
        missing for SILENT_AFTER_S (error; said once when it starts; not while the forwarder is restarted or
        silent, nor counted from before it answered: the silence is the bus's, and every node was said hung), it cannot
        start (error), it waits for what it needs (exit TEMPFAIL), waits to respawn or exited with an error
        code (warn)."""
        faults = []
        bus_down = (self._forwarder_start is not None or self._forwarder_retry_at is not None
                    or bool(self._silent_forwarder))
        for child in self.children:
            name, kind, fault, state = child.spec.name, "", "", "warn"
            running = child.proc is not None
            silent_s = (None if not running or child.last_status_s is None or bus_down
                        else now - max(child.last_status_s, self._bus_back_s))  # a forwarder's gap is not theirs
            if running and process_state(child.proc.pid) in ("T", "t"):
                kind, fault, state = "stopped", f"{name} is stopped (SIGSTOP?)", "error"
            elif silent_s is not None and silent_s > SILENT_AFTER_S:
                kind, fault, state = "silent", f"{name} sent no /status for {silent_s:.0f} s (hung?)", "error"
            elif child.waiting_since is not None:
                fault = f"{name} waits ({now - child.waiting_since:.0f} s): {child.error}"
            elif child.cannot_run:
                fault, state = f"{name} {_cannot(child)}: {child.error}", "error"
            elif not running and child.restart_at is not None:
                fault = f"{name} exited with code {child.exit_code}; respawning"
            elif not running and child.exit_code:
                fault = f"{name} exited with code {child.exit_code}"
            if kind and kind != child.fault:
                self.say(fault)
            child.fault = kind
            if fault:
                faults.append((state, fault))
        return faults

    def _publish_status(self, now: float) -> None:
        """The launcher's NodeStatus: node faults, respawn and forwarder restart counts."""
        from msgs import NodeStatus

        faults = self._check_nodes(now)
        state = "error" if any(s == "error" for s, _ in faults) else ("warn" if faults else "ok")
        counters = {"respawns": sum(c.retries for c in self.children), "forwarder_restarts": self.forwarder_restarts,
                    "running": sum(c.proc is not None for c in self.children),
                    "waiting": sum(c.waiting_since is not None for c in self.children),
                    **{f"{c.spec.name}.respawns": c.retries for c in self.children if c.retries}}
        self._status_pub.publish(STATUS_TOPIC, NodeStatus(
            stamp_ns=time.time_ns(), state=state, message="; ".join(m for _, m in faults), pid=os.getpid(),
            uptime_s=now - self._started, publishes=[[STATUS_TOPIC, "NodeStatus"]],
            subscribes=[[STATUS_TOPIC, "NodeStatus"]], counters=counters), latched=True)

    def _exited(self, child: Child, now: float) -> None:
        """Respawn a node whose process has exited, let it wait, give up on it, or stop the launch,
        by its exit code (module docstring)."""
        spec, code = child.spec, child.proc.returncode
        failed_start = code == CONFIG and child.last_status_s is None
        child.exit_code = code
        _signal_group(child.proc, signal.SIGTERM)  # what it started and left (it was killed or crashed)
        child.proc = None
        if child.reader is not None:
            child.reader.join(1.0)
        if self._stop.is_set():
            return
        child.error = _error_of(child.lines)
        child.start_failures = child.start_failures + 1 if failed_start else 0
        can_respawn = spec.respawn and (spec.max_retries is None or child.retries < spec.max_retries)
        if can_respawn and code == TEMPFAIL:
            child.retries += 1
            self._wait(child, now)
            return
        child.waiting_since, child.quiet = None, set()
        if code == CONFIG_WHILE_RUNNING or (failed_start and (not can_respawn or child.start_failures >= START_TRIES)):
            self._cannot_run(child, now)
            return
        if can_respawn:
            child.retries += 1
            exited = f"{spec.name} exited with code {code}" + (
                f" at its start (a configuration error, {child.start_failures} of {START_TRIES} tries)"
                if failed_start else "")
            if self._promote_spare(child, now, exited):
                return
            child.restart_at = now + spec.respawn_delay_s
            self.say(f"{exited}; respawn {child.retries} in {spec.respawn_delay_s:g} s")
            return
        self.say(f"{spec.name} exited with code {code}" + (" (no retries left)" if spec.respawn else "")
                 + (": not ready (`respawn: true` waits for it)" if code == TEMPFAIL and not spec.respawn else ""))
        if spec.required:
            self.say(f"{spec.name} is required: stopping the launch")
            self.exit_code = OK if code == OK else FAILED  # a replay's player that has played its bag ends it well
            self._stop.set()

    def _wait(self, child: Child, now: float) -> None:
        """Start a node that exited with TEMPFAIL (what it needs is not there yet) again after its
        respawn delay, for as long as it takes: said when it starts waiting, its tries then quiet."""
        spec = child.spec
        child.restart_at = now + spec.respawn_delay_s
        child.quiet.update(map(_numbers_masked, child.lines))
        child.error = child.error or "not ready"
        if child.waiting_since is None:
            child.waiting_since = now
            self.say(f"{spec.name} is not ready (exit {TEMPFAIL}): starting it again every {spec.respawn_delay_s:g} s "
                     "until it is up, without repeating its output")

    def _cannot_run(self, child: Child, now: float) -> None:
        """Stop the launch, with CONFIG, for a node whose start failed with a configuration error
        START_TRIES times in a row (or that has no respawn left), or that found one while running (exit
        CONFIG_WHILE_RUNNING): the launch as configured cannot run, whatever `required` says (README,
        "Launch files")."""
        child.cannot_run = True
        child.error = child.error or f"exit code {child.exit_code}"
        tries = ("found while running" if child.exit_code == CONFIG_WHILE_RUNNING
                 else f"{child.start_failures} tries in a row" if child.start_failures >= START_TRIES
                 else "no retries left" if child.spec.respawn else "no respawn")
        self.say(f"{child.spec.name} {_cannot(child)}: {child.error} (a configuration error, {tries}); "
                 "stopping the launch")
        self.exit_code = CONFIG
        self._publish_status(now)  # the reason, latched on /status for whoever watches it
        self._stop.set()

    def _shutdown(self) -> None:
        """Stop the nodes and their spares: SIGTERM to each process group once its process can take it
        (`_terminate_when_ready`; to the rest `TERM_WAIT_S` before the grace time ends: sent at its end, each was
        killed at once, said as one that did not stop), SIGKILL to those still running `GRACE_S` after the stop;
        then the forwarder.
        Each exit code is said with `-v` (debug); one ended by a signal, or killed, at any level."""
        spares = [c for c in self.children if c.spare is not None]
        running = [c for c in self.children if c.proc is not None]
        deadline = time.monotonic() + GRACE_S
        _terminate_when_ready([c.spare for c in spares] + [c.proc for c in running], deadline - TERM_WAIT_S)
        for child in running:
            self._end(child.proc, child.spec.name, deadline)
            if child.reader is not None:
                child.reader.join(1.0)
            child.proc = None
        for child in self.children:
            child.restart_at = child.spare_at = None
        for child in spares:
            self._end(child.spare, f"spare {child.spec.name}", deadline)
            child.spare = None
        for sock in (self._status_reader, self._param_reader, self._params, self._status_pub):
            if sock is not None:
                sock.close()
        self._status_reader = self._param_reader = self._params = self._status_pub = None
        if self._forwarder_start is not None:  # a restart not answered yet: stopped and reaped, not said
            self._forwarder_start.stop()
            self._forwarder_start = None
        if self._forwarder is not None:
            self._forwarder.terminate()
            try:
                self._forwarder.wait(FORWARDER_GRACE_S)
                self._say_exit(self._forwarder, "forwarder")
            except subprocess.TimeoutExpired:
                self.say(f"forwarder did not stop within {FORWARDER_GRACE_S} s: killed")
                self._forwarder.kill()
                self._forwarder.wait()
            self._forwarder = None

    def _end(self, proc: subprocess.Popen, who: str, deadline: float) -> None:
        """Wait until `deadline` for `proc` (`who`: a node or spare), sent SIGTERM, to exit, then kill its
        process group (said); `_say_exit` otherwise."""
        try:
            proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            self.say(f"{who} did not stop within {GRACE_S} s: killed")
            _signal_group(proc, signal.SIGKILL)
            proc.wait()
            return
        self._say_exit(proc, who)

    def _say_exit(self, proc: subprocess.Popen, who: str) -> None:
        """Say how `proc` (`who`) that the shutdown stopped ended: its exit code with `-v` (debug), at any level
        when a signal ended it (a stop it could not take)."""
        if proc.returncode < 0:
            self.say(f"{who} pid {proc.pid} was ended by a signal: {signal.strsignal(-proc.returncode)} "
                     f"(exit {proc.returncode})")
        elif _log.isEnabledFor(logging.DEBUG):
            self.say(f"{who} pid {proc.pid} exited with code {proc.returncode}")


def _cannot(child: Child) -> str:
    """What a node that ends the launch could not do: start, or go on (it found the error while running)."""
    return "cannot go on" if child.exit_code == CONFIG_WHILE_RUNNING else "cannot start"


def _error_of(lines: list[str]) -> str:
    """The error a node's process said: its last line, without the `fv node: error: ` (or `not ready: `)
    the command line writes before it; "" when it said nothing."""
    last = next((line.strip() for line in reversed(lines) if line.strip()), "")
    for prefix in ("fv node: error: ", "fv node: not ready: "):
        last = last.removeprefix(prefix)
    return last


def _numbers_masked(line: str) -> str:
    """`line` with each run of digits as "#": a waiting node's tries that differ only in their numbers
    (the time in OpenCV's `[ WARN:0@2.062]`) say the same."""
    return re.sub(r"\d+", "#", line)


def _terminate_when_ready(procs: list[subprocess.Popen], deadline: float) -> None:
    """Send SIGTERM to the process group of each of `procs` as soon as its process catches or ignores it
    (`_takes_sigterm`) or has exited, the rest at `deadline`. A node started in the last 0.1 to 0.4 s before a
    stop (a first start, a respawn, a spare) had not yet installed the handlers of `fv` (Python still loading
    `nodes.cli`): the signal ended it (-15) instead of stopping it cleanly. A process that takes SIGTERM is sent
    it at once: a normal stop waits for nothing."""
    pending = list(procs)
    while pending:
        late = time.monotonic() >= deadline
        for proc in [p for p in pending if late or p.poll() is not None or _takes_sigterm(p.pid)]:
            _signal_group(proc, signal.SIGTERM)
            pending.remove(proc)
        if pending:
            time.sleep(READY_POLL_S)


def _takes_sigterm(pid: int) -> bool:
    """Whether process `pid` catches SIGTERM (a handler installed) or ignores it, by /proc/PID/status
    (SigCgt, SigIgn: hexadecimal masks, bit n - 1 for signal n); True where that cannot be read (no /proc;
    the process gone), so that it is sent at once, as before."""
    try:
        with open(f"/proc/{pid}/status") as f:
            masks = dict(line.split(":", 1) for line in f if line.startswith(("SigCgt:", "SigIgn:")))
        return bool((int(masks["SigCgt"], 16) | int(masks["SigIgn"], 16)) >> (signal.SIGTERM - 1) & 1)
    except (OSError, KeyError, ValueError):
        return True


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    """Send `sig` to the process group `proc` leads (its children included)."""
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("launch", help="run a launch file: fv launch FILE [name:=value ...]")
    # a missing file is said by _launch: argparse's error named the optional name:=value as required too
    p.add_argument("file", type=Path, nargs="?", help="launch file (YAML), e.g. launch/demo.yaml")
    p.add_argument("args", nargs="*", metavar="name:=value", help="launch argument overrides")
    p.add_argument("--check", action="store_true", help="validate the file and list its nodes; start nothing")
    p.set_defaults(func=_launch, intermixed="args")


def _launch(args: argparse.Namespace) -> int:
    if args.file is None:
        raise ValueError("no launch file given: fv launch FILE [name:=value ...]")
    launch = Launch.from_file(args.file, parse_arg_overrides(args.args))  # LaunchError: `fv` prints it, exit 2
    if args.check:
        for spec in launch.specs:
            where = (f" namespace={spec.namespace}" if spec.namespace else "") + (
                f" remap={spec.remap}" if spec.remap else "")
            path = f" ({spec.path})" if spec.namespace else ""  # the name `fv param` also takes
            print(f"{spec.name}{path}: {spec.kind}{where} params={spec.params} ({spec.source})")
        return OK
    return launch.run()
