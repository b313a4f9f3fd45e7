"""The `fv` command line. Each command group lives in its own module exposing
`register(subparsers)`; those modules import heavy libraries (torch, cv2) only inside
the command functions so `fv --help` stays fast."""
from __future__ import annotations

import argparse
import importlib
import logging
import multiprocessing
import os
import signal
import sys
import threading

from fv_algos.allocator import steady_malloc
from nodes.exit_codes import (CONFIG, CONFIG_WHILE_RUNNING, FAILED, OK, TEMPFAIL, NodeFailed, NotReadyError,
                              Stopped, interrupted_code, on_stop_signals, stop_signals, stopping)
from nodes.parent_death import stop_with_parent

COMMAND_MODULES = [
    "nodes.core_commands",
    "nodes.sim_commands",
    "nodes.launcher",
    "nodes.topic_tools",
    "nodes.param_commands",
    "nodes.bag.commands",
    "nodes.bench_commands",
    "nodes.slip_commands",
    "nodes.real_commands",
    "nodes.view_commands",
]

STOP_ENDS_WELL = ("launch", "forwarder")  # commands that run until stopped: a stop is their clean end (exit OK),
# also one that came as the command line imported its modules (README: `fv launch` stopped by Ctrl-C exits 0); named
# here, by the command word, not where the commands are registered: such a stop comes before their modules are imported


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fv", description="FingerVision tactile sensing tools")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The parsed command line. A command that sets the default `intermixed` (the name of its list of
    positionals) also takes them after its options: `fv launch FILE --check name:=value`."""
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    field = getattr(args, "intermixed", None)
    if extra and field and not any(item.startswith("-") for item in extra):
        getattr(args, field).extend(extra)
    elif extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    return args


def _stop_command(signum: int) -> None:
    """A command's stop on the first of `stop_signals()` (`on_stop_signals`; nodes, launches and the forwarder
    put their own in its place): the worker processes of the command's process pools are terminated (a
    `kill` of this process did not reach them: a benchmark's worker ran on for 80 s; SIGINT, as Ctrl-C gives
    them, only ended the task it was on, and the pool waited for the worker), then `Stopped` (a
    KeyboardInterrupt) is raised. The pools' threads then find their workers gone, which they are not told of
    (`_quiet_pool_threads`). A multiprocessing.Pool's workers are left to its exit. The stop signals that
    come after it are ignored (`ignore_stop_signals`): one during the clean-up cut it short, also after Ctrl-C
    (`fv sim --out` left its partial folder of PNGs behind)."""
    threading.excepthook = _quiet_pool_threads
    for child in multiprocessing.active_children():
        if "PoolWorker" not in child.name:  # a multiprocessing.Pool's: its exit ends them (it replaced those ended here)
            child.terminate()
    raise Stopped(signum)


def _quiet_pool_threads(args: threading.ExceptHookArgs) -> None:
    """After a stop: a process pool's thread that finds the workers ended by `_stop_command` raises (in
    Python 3.11, InvalidStateError for the futures the stop cancelled); other errors are printed as ever."""
    from concurrent.futures import InvalidStateError
    from concurrent.futures.process import BrokenProcessPool
    if not issubclass(args.exc_type, (InvalidStateError, BrokenProcessPool)):
        threading.__excepthook__(args)


def main(argv: list[str] | None = None) -> int:
    """Run the command; its exit code (`nodes.exit_codes`): a NotReadyError gives TEMPFAIL, an error
    of input or configuration (ValueError, KeyError, OSError, RuntimeError) CONFIG, each said in one line;
    Ctrl-C INTERRUPTED, SIGTERM and SIGHUP 128 + their number (OK for the commands of `STOP_ENDS_WELL`: a launch
    stopped as it imported exited 130), after the command's clean-up, the stop signals
    after the first ignored to the process's exit. The stop handlers are in place before the command modules
    are imported (0.25 s on an idle host, seconds as a launch starts its nodes on 2 cores): a SIGTERM during
    those imports ended the process by the signal (-15) instead. A process started by `fv launch`
    (`nodes.parent_death`) gets SIGTERM when its launcher dies."""
    in_main_thread = threading.current_thread() is threading.main_thread()  # (tests call main() in threads too)
    previous = {sig: signal.getsignal(sig) for sig in stop_signals()} if in_main_thread else {}
    if in_main_thread:
        on_stop_signals(_stop_command)
    try:
        return _run(argv)
    except KeyboardInterrupt as stop:  # Ctrl-C, or `Stopped`
        command = _command_word(sys.argv[1:] if argv is None else argv)
        return OK if command in STOP_ENDS_WELL else interrupted_code(stop)
    finally:
        if not stopping():  # once stopping, this process ignores them to its exit (`ignore_stop_signals`)
            for sig, handler in previous.items():  # a caller's own (main() called in a test's process)
                signal.signal(sig, handler)


def _command_word(argv: list[str]) -> str | None:
    """The command `argv` names (its first word that is not an option; `fv` has no option taking a value),
    known before the command modules are imported: None when it names none."""
    return next((word for word in argv if not word.startswith("-")), None)


def _run(argv: list[str] | None) -> int:
    """Parse `argv` and run its command (`main`, which handles its stop); the exit code of its errors."""
    args = parse_args(argv)
    steady_malloc()  # every fv process: nodes, training, benchmarks
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="[%(name)s] %(levelname)s: %(message)s", stream=sys.stderr)
    try:
        stop_with_parent()  # with the stop handlers in place: the launcher's death is a clean stop
        return int(args.func(args) or OK)
    except BrokenPipeError:  # `fv bag info x | head`: the reader has gone, nothing to say to it
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        return FAILED
    except NodeFailed as exc:  # a configuration error a running node found: a launch stops, not respawns it
        print(f"fv {args.command}: error: {exc}", file=sys.stderr)
        return CONFIG_WHILE_RUNNING
    except NotReadyError as exc:  # a camera not plugged in yet: `fv launch` starts the node again, quietly
        print(f"fv {args.command}: not ready: {exc}", file=sys.stderr)
        return TEMPFAIL
    except (ValueError, KeyError, OSError, RuntimeError) as exc:  # OSError: a disk full, a folder gone mid-run, ...
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        logging.getLogger("fv").debug("the error's traceback", exc_info=True)
        print(f"fv {args.command}: error: {msg}", file=sys.stderr)
        return CONFIG


if __name__ == "__main__":
    sys.exit(main())
