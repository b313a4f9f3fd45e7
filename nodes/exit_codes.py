"""The exit codes of `fv` commands and nodes, one definition for the command line, the nodes and
the launcher, which respawns a node by what its code says (README, "Launch files"); and the signals
that stop them.

OK: done, or stopped cleanly (Ctrl-C, SIGTERM). FAILED: an unexpected failure (a traceback), a
launch whose required node failed, `fv topic echo --timeout` that got no message, output whose reader went
away (a broken pipe). CONFIG: a configuration error (a bad argument, param, launch file, model or video, a
bus another forwarder serves), found before or at the start, that will come again until the configuration
changes. TEMPFAIL (sysexits.h's EX_TEMPFAIL): what the process needs is not there yet and may come
without a change of configuration (a camera not plugged in, or busy); start it again later.
CONFIG_WHILE_RUNNING (sysexits.h's EX_CONFIG): a configuration error a running node found, which a
restart would meet again (a simulated scene whose next frame cannot be played: `NodeFailed`).
INTERRUPTED: Ctrl-C outside a node's own handler (128 + SIGINT); SIGTERM and SIGHUP give 128 + their
number in the same way (`Stopped`).
"""
from __future__ import annotations

import atexit
import os
import signal
from types import FrameType
from typing import Callable

OK = 0
FAILED = 1
CONFIG = 2
TEMPFAIL = 75
CONFIG_WHILE_RUNNING = 78
INTERRUPTED = 130

_stopped_by: int | None = None  # the first of `stop_signals()` to come (`ignore_stop_signals`)


def stop_signals() -> tuple[int, ...]:
    """The signals that stop a node, a launch or a command cleanly: SIGINT, SIGTERM and SIGHUP (its terminal
    closed; a recorder left its bag unfinished), but SIGHUP not where it is ignored: `nohup fv ...` runs on
    after the terminal closes (each stopped on SIGHUP, whatever nohup said)."""
    ignored = signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    return (signal.SIGINT, signal.SIGTERM) + (() if ignored else (signal.SIGHUP,))


def on_stop_signals(stop: Callable[[int], None]) -> None:
    """Call `stop(signum)` on the first of `stop_signals()` to come (call it from the main thread): one
    definition of a stop for every `fv` process, the command line's (`nodes.cli`) as a node's, a launcher's or
    the forwarder's. The process then ignores them all to its exit (`ignore_stop_signals`). Where one has come
    already, `stop` is called at once: the command line's `Stopped`, raised in a node still importing, was
    lost where Python ignores exceptions (a weakref callback of the import system: 1 run in 10 of two SIGTERMs
    50 ms apart as `fv node talker` started), and the node then ran on as if it had not been stopped.

    A process forked from this one (a pool's worker) inherits the handler: there, a stop signal acts as
    Python's default would, SIGINT raising KeyboardInterrupt and SIGTERM or SIGHUP ending it by the signal,
    its files being written removed first (a terminated worker left a `*.tmp.npz` in the field cache), so
    that its parent's `terminate()` still ends it (a node's worker ran the node's stop on its copy, then
    ignored them)."""
    if _stopped_by is not None:
        stop(_stopped_by)
        return
    installer = os.getpid()

    def handler(signum: int, frame: FrameType | None) -> None:
        if os.getpid() != installer:
            _stop_by_default(signum, frame)
        elif _stopped_by is None:  # (a run inside the first one's, once that has begun, does nothing)
            ignore_stop_signals(signum)
            stop(signum)

    for sig in stop_signals():
        signal.signal(sig, handler)


def ignore_stop_signals(signum: int) -> None:
    """This process is stopping on `signum`: ignore every stop signal from now on, to the process's exit, where
    `kill -9` still ends it. A stop signal run inside its first one's handler deadlocked it in
    threading.Event.set, on the lock that run held: a forwarder whose launcher was killed ran on for good
    (1 run in 11); one that came during a command's clean-up cut it short (a partial `fv sim --out` folder
    left); one that came once `nodes.cli.main` had returned, its handlers restored, ended the process by the
    signal (exit -15 where 0 or 143 was due). The kernel sends a launched process SIGTERM once per thread of
    its dying launcher (`nodes.parent_death`); a process in a terminal's process group gets Ctrl-C's SIGINT,
    then its launcher's SIGTERM; supervisors send SIGTERM again.

    They are ignored by a handler that does nothing, and by the system only at the exit (atexit), as the
    interpreter's finalisation resets handlers written in Python to the default: a stop signal that had come
    but whose handler had not yet run when the system was told to ignore them was reported as an error
    ("OSError: Signal 15 ignored due to race condition": SIGINT and SIGTERM at once to a forwarder, 7 runs of
    10)."""
    global _stopped_by
    if _stopped_by is None:
        _stopped_by = signum
        atexit.register(_ignore_to_the_exit)
    for sig in stop_signals():
        signal.signal(sig, _ignore)


def stopping() -> bool:
    """Whether one of `stop_signals()` has come to this process (`ignore_stop_signals`)."""
    return _stopped_by is not None


def _ignore(_signum: int, _frame: FrameType | None) -> None:
    """The handler of the stop signals once the process is stopping."""


def _ignore_to_the_exit() -> None:
    """Have the system ignore the stop signals, through the interpreter's finalisation."""
    for sig in stop_signals():
        signal.signal(sig, signal.SIG_IGN)


def _stop_by_default(signum: int, frame: FrameType | None) -> None:
    """Python's default for stop signal `signum` in a process without handlers: KeyboardInterrupt for
    SIGINT, else the end of the process by the signal (which runs no `finally`: the files it is writing are
    removed first)."""
    if signum == signal.SIGINT:
        signal.default_int_handler(signum, frame)
    from fv_algos.atomic_file import remove_partial_files
    remove_partial_files()
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)


class Stopped(KeyboardInterrupt):
    """A stop signal (Ctrl-C's SIGINT; SIGTERM or SIGHUP: `kill`, systemd, `timeout`, a closed terminal), raised
    where the command runs, so that it stops as on Ctrl-C: its clean-up runs (a partial output folder is removed)
    and it exits 128 + the signal's number. Before, SIGTERM ended it at once, leaving a half-written `fv sim
    --out` folder behind. A subclass for SIGINT too: CPython notes a KeyboardInterrupt itself (not a subclass)
    that leaves Python code run by a C extension (PyRun_String: pybind11's exec), and a process run as `python
    -m` then kills itself by SIGINT at its exit whatever it caught and returned (a launch or node stopped by
    Ctrl-C as it imported exited -2, with no word)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.exit_code = 128 + signum


def interrupted_code(stop: KeyboardInterrupt) -> int:
    """The exit code of a process that `stop` ended: 128 + the signal's number for `Stopped`,
    INTERRUPTED for a KeyboardInterrupt of Python's own SIGINT handler (before `fv`'s are in place)."""
    return stop.exit_code if isinstance(stop, Stopped) else INTERRUPTED


class NodeFailed(RuntimeError):
    """Raised by `Node.spin` when the node stopped through `Node.fail`; the message is the error. The
    command exits CONFIG_WHILE_RUNNING."""


class NotReadyError(RuntimeError):
    """What a process needs is not there yet (a camera not plugged in, a device busy) and may come
    without a change of configuration: the command exits TEMPFAIL, saying this error's message."""
