"""`stop_process`: end a child process with a signal, SIGKILL after a timeout, and reap it."""
from __future__ import annotations

import signal
import subprocess

STOP_TIMEOUT_S = 30.0  # how long a process may take to exit after its signal before it is killed


def stop_process(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout_s: float = STOP_TIMEOUT_S) -> int:
    """Send `sig` to `proc`, SIGKILL it if it has not exited after `timeout_s`; its return code."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode
