"""The exit codes of `fv` commands and nodes, one definition for the command line, the nodes and
the launcher, which respawns a node by what its code says (README, "Launch files"); and the signals
that stop them.

OK: done, or stopped cleanly (Ctrl-C, SIGTERM). FAILED: an unexpected failure (a traceback), a
launch whose required node failed. CONFIG: a configuration error (a bad argument, param, launch
file, model or video), found before or at the start, that will come again until the configuration
changes. TEMPFAIL (sysexits.h's EX_TEMPFAIL): what the process needs is not there yet and may come
without a change of configuration (a camera not plugged in, or busy); start it again later.
CONFIG_WHILE_RUNNING (sysexits.h's EX_CONFIG): a configuration error a running node found, which a
restart would meet again (a simulated scene whose next frame cannot be played: `NodeFailed`).
INTERRUPTED: Ctrl-C outside a node's own handler (128 + SIGINT); SIGTERM and SIGHUP give 128 + their
number in the same way (`nodes.cli.Stopped`).
"""
from __future__ import annotations

import signal
from types import FrameType
from typing import Callable

OK = 0
FAILED = 1
CONFIG = 2
TEMPFAIL = 75
CONFIG_WHILE_RUNNING = 78
INTERRUPTED = 130


def stop_signals() -> tuple[int, ...]:
    """The signals that stop a node, a launch or a command cleanly: SIGINT, SIGTERM and SIGHUP (its terminal
    closed; a recorder left its bag unfinished), but SIGHUP not where it is ignored: `nohup fv ...` runs on
    after the terminal closes (each stopped on SIGHUP, whatever nohup said)."""
    ignored = signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
    return (signal.SIGINT, signal.SIGTERM) + (() if ignored else (signal.SIGHUP,))


def on_stop_signals(stop: Callable[[], None]) -> None:
    """Call `stop()` on the first of `stop_signals()`, the rest then ignored (call it from the main thread).
    A handler run again inside its own first run, as Python runs a signal that comes while its handler runs,
    deadlocked in threading.Event.set, which takes a lock that the first run held: a forwarder whose
    launcher was killed ran on for good (1 run in 11). The kernel sends a launched process SIGTERM once per
    thread of its dying launcher (`nodes.parent_death`); a forwarder in a terminal's process group gets
    Ctrl-C's SIGINT, then its launcher's SIGTERM."""
    signals = stop_signals()

    def handler(_signum: int, _frame: FrameType | None) -> None:
        for sig in signals:
            signal.signal(sig, signal.SIG_IGN)
        stop()

    for sig in signals:
        signal.signal(sig, handler)


class NodeFailed(RuntimeError):
    """Raised by `Node.spin` when the node stopped through `Node.fail`; the message is the error. The
    command exits CONFIG_WHILE_RUNNING."""


class NotReadyError(RuntimeError):
    """What a process needs is not there yet (a camera not plugged in, a device busy) and may come
    without a change of configuration: the command exits TEMPFAIL, saying this error's message."""
