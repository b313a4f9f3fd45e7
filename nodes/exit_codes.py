"""The exit codes of `fv` commands and nodes, one definition for the command line, the nodes and
the launcher, which respawns a node by what its code says (README, "Launch files").

OK: done, or stopped cleanly (Ctrl-C, SIGTERM). FAILED: an unexpected failure (a traceback), a
launch whose required node failed. CONFIG: a configuration error (a bad argument, param, launch
file, model or video), found before or at the start, that will come again until the configuration
changes. TEMPFAIL (sysexits.h's EX_TEMPFAIL): what the process needs is not there yet and may come
without a change of configuration (a camera not plugged in, or busy); start it again later.
INTERRUPTED: Ctrl-C outside a node's own handler (128 + SIGINT); SIGTERM and SIGHUP give 128 + their
number in the same way (`nodes.cli.Stopped`).
"""
from __future__ import annotations

OK = 0
FAILED = 1
CONFIG = 2
TEMPFAIL = 75
INTERRUPTED = 130


class NotReadyError(RuntimeError):
    """What a process needs is not there yet (a camera not plugged in, a device busy) and may come
    without a change of configuration: the command exits TEMPFAIL, saying this error's message."""
