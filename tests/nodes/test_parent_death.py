"""A process started with `parent_env()` stops when its parent dies (`nodes.parent_death`): by the
kernel's parent-death signal, by the watcher thread where there is none, and at once when the parent
died before it asked."""
from __future__ import annotations

import os
import select
import signal
import subprocess
import sys

import pytest

from nodes.exit_codes import OK
from nodes.parent_death import PARENT_PID_ENV
from nodes.proc_stats import process_alive
from tests.nodes.conftest import REPO, Bus, wait_for

# a parent that starts a child (argv[1]) tied to its life, and sleeps; the child, once it has asked (HOW: by
# the kernel, or the watcher where there is none), says its pid (on the parent's stdout) and sleeps
PARENT = ("import os, subprocess, sys, time; from nodes.parent_death import parent_env; "
          "subprocess.Popen([sys.executable, '-c', sys.argv[1]], env={**os.environ, **parent_env()}); time.sleep(60)")
CHILD = ("import os, time; import nodes.parent_death as p; "
         "p._kernel_signals_parent_death = (lambda: False) if HOW == 'watcher' else p._kernel_signals_parent_death; "
         "p.stop_with_parent(); print(os.getpid(), flush=True); time.sleep(60)")


@pytest.mark.parametrize("how", ["kernel", "watcher"])
def test_a_process_stops_when_its_parent_is_killed(how: str) -> None:
    """`kernel`: prctl(PR_SET_PDEATHSIG) on Linux; `watcher`: the fallback where there is no prctl (macOS)."""
    parent = subprocess.Popen([sys.executable, "-c", PARENT, CHILD.replace("HOW", repr(how))], cwd=REPO,
                              stdout=subprocess.PIPE, text=True, start_new_session=True)  # the child in its group
    try:
        assert select.select([parent.stdout], [], [], 30.0)[0], "the child did not say its pid within 30 s"
        child = int(parent.stdout.readline())
        assert process_alive(child)
        parent.kill()
        parent.wait(5.0)
        wait_for(lambda: not process_alive(child), 10.0, f"the child ({how}) ending with its parent", period_s=0.05)
    finally:
        try:
            os.killpg(parent.pid, signal.SIGKILL)  # the parent and the child, whatever failed
        except ProcessLookupError:
            pass
        parent.wait()


def test_a_node_whose_launcher_died_before_it_asked_stops_at_once(bus: Bus) -> None:
    """The launcher may die between a node's start and its prctl call: the node, re-parented, then finds
    another parent than the launcher named, and stops at its start (SIGTERM: exit 143) rather than run for
    good."""
    launcher = subprocess.Popen(["true"])
    launcher.wait()  # a launcher that has died
    env = {**os.environ, PARENT_PID_ENV: str(launcher.pid)}
    result = subprocess.run([sys.executable, "-m", "nodes.cli", "node", "talker"], cwd=REPO, env=env,
                            capture_output=True, text=True, timeout=30)
    assert result.returncode == 128 + 15 != OK, result.stderr
    assert f"the process that started this one (pid {launcher.pid}) is gone" in result.stderr  # it said nothing
