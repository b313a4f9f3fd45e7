"""`fv param list | get | set`: read and change running nodes' params (`nodes.param_service`), as ROS's
`ros2 param`; a node is named as `fv node list` shows it or by its ROS-style path (`/left/slip_detector`).
Exit 0 when answered; a refused value or a node that does not answer is an error naming it as typed."""
from __future__ import annotations

import argparse
import json
from typing import Any

from msgs.param import ParamState
from nodes.arg_types import positive_float
from nodes.param_service import ANSWER_TIMEOUT_S

NODE_HELP = ("node name as `fv node list` shows it (slip_detector, left_slip_detector) or its path as in ROS "
             "(/left/slip_detector: the node slip_detector a launch puts in the namespace left)")


def _row(state: ParamState, name: str) -> str:
    """One param as `fv param list / get` print it: `  threshold: 0.5  (live)`."""
    return f"  {name}: {json.dumps(state.params[name])}" + ("  (live)" if name in state.live else "")


def _print_node(node: str, state: ParamState | None) -> None:
    print(f"{node}:")
    if state is None:
        print("  (no params answer)")
        return
    if not state.params:  # a launcher's status name (`launch_pipeline`)
        print("  (no params)")
    for name in sorted(state.params):
        print(_row(state, name))


def _as_dict(state: ParamState | None) -> dict[str, Any] | None:
    return None if state is None else {"params": state.params, "live": state.live}


def _list(args: argparse.Namespace) -> int:
    from nodes.param_service import read_all_params, read_params
    from nodes.topic_tools import discover

    if args.node:
        states = {args.node: read_params(args.node, args.timeout)}
    else:
        states = read_all_params(list(discover()), args.timeout)
    if args.json:
        print(json.dumps({node: _as_dict(state) for node, state in states.items()}))
        return 0
    for node, state in states.items():
        _print_node(node, state)
    return 0


def _get(args: argparse.Namespace) -> int:
    from nodes.param_service import read_params

    state = read_params(args.node, args.timeout)
    if args.name is None:
        if args.json:
            print(json.dumps(_as_dict(state)))
        else:
            _print_node(args.node, state)
        return 0
    if args.name not in state.params:
        raise KeyError(f"node {args.node!r} has no param {args.name!r}; its params: {sorted(state.params)}")
    print(json.dumps({"name": args.name, "value": state.params[args.name], "live": args.name in state.live})
          if args.json else json.dumps(state.params[args.name]))
    return 0


def _set(args: argparse.Namespace) -> int:
    from nodes.param_service import set_params
    from nodes.params import parse_text

    state = set_params(args.node, {args.name: parse_text(args.value)}, args.timeout)
    print(f"{args.node}: {args.name} set to {json.dumps(state.params[args.name])}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    param = sub.add_parser("param", help="read and set running nodes' params (list, get, set)")
    verbs = param.add_subparsers(dest="verb", required=True, metavar="VERB")

    def verb(name: str, help_text: str, func: Any) -> argparse.ArgumentParser:
        p = verbs.add_parser(name, help=help_text)
        p.set_defaults(func=func)
        p.add_argument("--timeout", type=positive_float, default=ANSWER_TIMEOUT_S,
                       help=f"seconds to wait for the node's answer (default {ANSWER_TIMEOUT_S:g})")
        return p

    p = verb("list", "params of every running node, or of NODE, '(live)' marking those `set` may change", _list)
    p.add_argument("node", nargs="?", default=None, help=NODE_HELP)
    p.add_argument("--json", action="store_true", help="machine-readable JSON output")
    p = verb("get", "a running node's params, or one of them", _get)
    p.add_argument("node", help=NODE_HELP)
    p.add_argument("name", nargs="?", default=None, help="param name (default: all)")
    p.add_argument("--json", action="store_true", help="machine-readable JSON output")
    p = verb("set", "set a live param of a running node: fv param set slip_detector threshold 0.7", _set)
    p.add_argument("node", help=NODE_HELP)
    p.add_argument("name", help="param name")
    p.add_argument("value", help="new value, read as YAML as on the command line (0.7, true, [1, 2])")
