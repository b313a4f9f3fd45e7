"""A process started by another `fv` process that owns it (the nodes, standby spares and forwarder of
`fv launch`) stops when that owner dies, however it dies: SIGKILL, the OOM killer, a crash.

The owner puts its pid in the environment of the process it starts (`parent_env()`); the process calls
`stop_with_parent()` once, early, with its stop handlers installed. From then on the owner's death
arrives as `STOP_SIGNAL` (SIGTERM), which every `fv` process already handles as a clean stop: a node
runs its teardown (a recorder finishes its bag), a spare and the forwarder exit, a command cleans up.

On Linux the kernel sends it (`prctl(PR_SET_PDEATHSIG)`), whatever the process's own threads are doing;
the owner may have died before the request, so the parent pid is checked after it. Where prctl is not
there (macOS), a thread compares the parent pid with the owner's every `WATCH_PERIOD_S`. On Linux the
signal comes when the owner's *thread* that started the process ends: an owner starts its processes from
threads that live as long as those processes should.

A started process that leads its own process group (a launched node or spare) takes its children with
it when it ends (`end_own_group`): a multiprocessing worker or a subprocess of a node would otherwise
outlive it, and its launcher.
"""
from __future__ import annotations

import atexit
import ctypes
import logging
import os
import signal
import sys
import threading
import time

PARENT_PID_ENV = "FV_PARENT_PID"  # the pid of the process that started this one and owns it
STOP_SIGNAL = signal.SIGTERM
WATCH_PERIOD_S = 0.2  # the fallback watcher's period (no prctl)
_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
_owner_pid: int | None = None  # the parent this process stops with (`stop_with_parent`)


def parent_env() -> dict[str, str]:
    """The environment entry that ties a process this one starts to this one's life."""
    return {PARENT_PID_ENV: str(os.getpid())}


def stop_with_parent() -> None:
    """Have `STOP_SIGNAL` sent to this process when the process named in `PARENT_PID_ENV` (its parent)
    dies, and at once when it has died already; nothing without that variable. The variable is removed
    from the environment: this process's own children have another parent."""
    global _owner_pid
    owner = os.environ.pop(PARENT_PID_ENV, None)
    if owner is None:
        return
    try:
        _owner_pid = owner_pid = int(owner)
    except ValueError:
        raise ValueError(f"{PARENT_PID_ENV}={owner!r} is not a process id") from None
    atexit.register(end_own_group)
    if not _kernel_signals_parent_death():
        threading.Thread(target=_watch_parent, args=(owner_pid,), name="fv-parent-watch", daemon=True).start()
    if os.getppid() != owner_pid:  # died before the request (this process was re-parented)
        logging.getLogger("fv").warning("the process that started this one (pid %d) is gone (the parent is pid %d "
                                        "now): stopping", owner_pid, os.getppid())
        os.kill(os.getpid(), STOP_SIGNAL)


def end_own_group() -> None:
    """Send `STOP_SIGNAL` to the rest of this process's group, its children, when this process was
    started by an owner (`stop_with_parent`) and leads the group; this process then ignores the
    signal: call it as the process ends (registered with atexit; call it before `os._exit`)."""
    if _owner_pid is None or os.getpgrp() != os.getpid():
        return
    signal.signal(STOP_SIGNAL, signal.SIG_IGN)
    os.killpg(os.getpid(), STOP_SIGNAL)


def _kernel_signals_parent_death() -> bool:
    """Ask the kernel for `STOP_SIGNAL` at the parent's death; False where it cannot be asked."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return False
    return prctl(_PR_SET_PDEATHSIG, int(STOP_SIGNAL), 0, 0, 0) == 0


def _watch_parent(owner_pid: int) -> None:
    """The fallback: send `STOP_SIGNAL` to this process once its parent is no longer `owner_pid`."""
    while os.getppid() == owner_pid:
        time.sleep(WATCH_PERIOD_S)
    os.kill(os.getpid(), STOP_SIGNAL)
