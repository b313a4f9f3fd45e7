"""`fv forwarder`, `fv node`, `fv keys`: run the bus and single nodes."""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

if TYPE_CHECKING:
    from nodes.node import Node


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("forwarder", help="run the bus forwarder (the launcher starts one when none runs)")
    p.add_argument("--tcp", metavar="tcp://HOST:PORT", help="also listen for other hosts (CURVE only)")
    p.add_argument("--keys", type=Path, help="CURVE key folder made by `fv keys` (needed with --tcp)")
    p.set_defaults(func=_forwarder)

    p = sub.add_parser("node", help="run one node: fv node KIND [--name N] [--param k=v ...]; "
                                    "`fv node kinds`, `fv node list [--json]`")
    p.add_argument("kind", help="node kind (see `fv node kinds`), or `list` for the running nodes")
    p.add_argument("--name", help="node name (default: the kind)")
    p.add_argument("--ns", default="", help="namespace for relative topic names")
    p.add_argument("--param", "-p", action="append", default=[], metavar="KEY=VALUE", help="override a param")
    p.add_argument("--params-json", default="", help="params as a JSON object (used by the launcher)")
    p.add_argument("--remap", "-r", action="append", default=[], metavar="FROM:=TO", help="rename a topic")
    p.add_argument("--json", action="store_true", help="with `list`: JSON output")
    p.add_argument("--wait", type=float, default=0.3, help="with `list`: seconds to collect node status")
    p.add_argument("--standby", action="store_true",
                   help="import the node's code, print a ready line and wait; run the node on SIGUSR1 "
                        "(the launcher's spare for `standby: true`)")
    p.set_defaults(func=_node)

    p = sub.add_parser("keys", help="create CURVE keys for a TCP bus")
    p.add_argument("folder", type=Path)
    p.set_defaults(func=_keys)


def _forwarder(args: argparse.Namespace) -> int:
    from nodes.forwarder import serve
    return serve(args.tcp, args.keys)


def parse_remaps(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        src, sep, dst = item.partition(":=")
        if not sep or not src or not dst:
            raise ValueError(f"remap {item!r} is not FROM:=TO")
        out[src] = dst
    return out


def _node(args: argparse.Namespace) -> int:
    """`fv node KIND`: run one node until it stops; exit FAILED when it ended in its own error (a player's
    damaged bag, a recorder's full disk: a launch whose required player failed exited 0, as if it had played
    its bag), OK otherwise."""
    from nodes.exit_codes import FAILED, OK, interrupted_code
    from nodes.params import parse_assignments
    from nodes.registry import NODES, node_class
    if args.kind == "kinds":
        print("\n".join(sorted(NODES)))
        return OK
    if args.kind == "list":
        from nodes.topic_tools import node_list
        return node_list(args)
    params = _json_params(args.params_json)
    params.update(parse_assignments(args.param))
    node = None
    try:
        cls = node_class(args.kind)
        if not args.standby or _wait_for_takeover(cls, params):
            node = cls(args.name or args.kind, params, namespace=args.ns, remap=parse_remaps(args.remap))
            node.spin()
        code = FAILED if node is not None and node.state == "error" else OK
    except KeyboardInterrupt as stop:  # stopped as it imported or set up (`Node.spin`), a spare as it preloaded
        code = interrupted_code(stop)
    _leave(node, code)


def _leave(node: Node | None, code: int) -> NoReturn:
    """End this node's process (`node`: the Node, None for a spare that did not take over) with exit `code`,
    once it has stopped. Python's own teardown of torch and numpy took the slip detector past the launcher's
    grace time when a whole launch stopped at once on 2 cores (it was killed on every Ctrl-C), and a spare
    0.4 to 1.0 s (the slip detector's, killed 1 run in 6): send what ZeroMQ still queues (the node's last
    frames and status, within the sockets' linger), flush, and leave without it (its children, which that
    teardown would have ended, with it)."""
    from nodes.bus import LINGER_MS, stop_handshake_watchers
    from nodes.parent_death import end_own_group
    stop_handshake_watchers()
    if node is not None:
        node.ctx.destroy(linger=LINGER_MS)
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    end_own_group()
    os._exit(code)


_JSON_KINDS = {list: "a list", str: "a string", bool: "a boolean", int: "a number", float: "a number",
               type(None): "null"}


def _json_params(text: str) -> dict:
    """The params of `--params-json TEXT` ({} for ""); ValueError naming the flag when TEXT is not
    JSON or not a JSON object."""
    if not text:
        return {}
    try:
        params = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--params-json is not JSON: {exc}") from None
    if not isinstance(params, dict):
        raise ValueError(f"--params-json must be a JSON object (got {_JSON_KINDS[type(params)]})")
    return params


def _wait_for_takeover(cls: type, params: dict, check_s: float = 0.5) -> bool:
    """Preload `cls` for `params`, print STANDBY_READY and block: True on SIGUSR1 (take over), False
    on SIGTERM / SIGINT (the launch is stopping, or the launcher died: `nodes.parent_death`), after which
    the stop signals are ignored as after any stop (`ignore_stop_signals`: a second SIGTERM 1 to 20 ms after
    the first ended the spare as it exited, -15, in 16 of 16 runs). A signal that another thread of the
    process took (the preload's, which do not block them) is handled, by `nodes.cli`'s handler, when the
    wait ends, within `check_s` seconds."""
    import signal

    from nodes.exit_codes import ignore_stop_signals
    from nodes.node import STANDBY_READY
    cls.preload(params)
    signals = {signal.SIGUSR1, signal.SIGTERM, signal.SIGINT}
    signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    print(STANDBY_READY, flush=True)
    received = None
    while received is None:
        received = signal.sigtimedwait(signals, check_s)
    take_over = received.si_signo == signal.SIGUSR1
    if not take_over:
        ignore_stop_signals(received.si_signo)  # before the unblock: a pending one is ignored as it comes
    signal.pthread_sigmask(signal.SIG_UNBLOCK, signals)
    return take_over


def _keys(args: argparse.Namespace) -> int:
    from nodes.endpoints import make_keys
    for path in make_keys(args.folder):
        print(path)
    return 0
