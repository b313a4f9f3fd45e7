"""`fv bench KIND ...`: the benchmarks, one sub-command each.

A benchmark is one line in `BENCHMARKS`: name -> (module, function). The function is
called as ``function(kinds, name)`` with the `fv bench` sub-parsers and adds its own
parser named `name` (flags, ``set_defaults(func=...)``); its module imports heavy
libraries only inside the command function, like every command module.
"""
from __future__ import annotations

import argparse
import importlib

BENCHMARKS: dict[str, tuple[str, str]] = {
    "bus": ("nodes.bench_bus", "add_parser"),
    "bag": ("nodes.bag.bench", "add_parser"),
    "perception": ("nodes.bench_perception", "add_parser"),
    "slip": ("nodes.slip_commands", "add_bench_parser"),
    "pipeline": ("nodes.bench_pipeline", "add_parser"),
    "soak": ("nodes.bench_soak", "add_parser"),
    "judge": ("nodes.bench_judge", "add_parser"),
}


def register(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="benchmarks (fv bench KIND --help)")
    kinds = bench.add_subparsers(dest="bench", required=True, metavar="KIND")
    for name, (module, function) in BENCHMARKS.items():
        getattr(importlib.import_module(module), function)(kinds, name)
