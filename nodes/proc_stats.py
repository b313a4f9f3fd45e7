"""State, CPU time and memory of a running process, read from /proc (Linux)."""
from __future__ import annotations

import os
from pathlib import Path

_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def _stat_fields(pid: int) -> list[str]:
    """The fields of /proc/`pid`/stat after the command name (the state letter first); OSError when it is gone."""
    return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()


def process_state(pid: int) -> str:
    """The state letter of process `pid` from /proc (R, S, D, T stopped...; "" if gone, also when it is reaped
    between the open and the read of its stat file)."""
    try:
        return _stat_fields(pid)[0]
    except (OSError, IndexError):
        return ""


def process_alive(pid: int) -> bool:
    """True when process `pid` exists and is not a zombie."""
    return process_state(pid) not in ("", "Z")


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds process `pid` has used so far; OSError when it is gone."""
    fields = _stat_fields(pid)
    return (int(fields[11]) + int(fields[12])) * _TICK_S


def memory_bytes(pid: int) -> tuple[int, int]:
    """(resident set size now, peak resident set size) of process `pid` in bytes;
    OSError when it is gone."""
    values = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = int(rest.split()[0]) * 1024  # reported in kB
    return values.get("VmRSS", 0), values.get("VmHWM", 0)
