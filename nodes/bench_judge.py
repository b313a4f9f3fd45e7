"""`fv bench judge`: the online trial model's cost per frame for several network shapes.

The slip detector runs the trial model (:class:`fv_algos.grasp_judge.GraspJudge`) once per field.
This times the network's part of a frame, :meth:`GraspJudge.push` on random descriptor rows (the
contact motion and field rows, measured elsewhere, are left out), for every combination of
temporal convolutions (``--layers``) and ensemble members (``--members``), on one torch thread as
the node runs it. The shapes take turns in every repeat, so each sees the same machine load; a
row's figure is its fastest repeat, and its ratio is to the first shape's.
"""
from __future__ import annotations

import argparse
import json
import time

from nodes.arg_types import positive_int


def add_parser(kinds: argparse._SubParsersAction, name: str) -> None:
    """Add `fv bench NAME` (an entry of nodes.bench_commands.BENCHMARKS)."""
    p = kinds.add_parser(name, help="online trial model (grasp judge): time per frame per network shape")
    p.add_argument("--layers", type=positive_int, nargs="+", default=[3, 4], help="temporal convolutions (default 3 4)")
    p.add_argument("--members", type=positive_int, nargs="+", default=[1, 5], help="ensemble members (default 1 5)")
    p.add_argument("--hidden", type=positive_int, default=16, help="channels per member (default 16)")
    p.add_argument("--frames", type=positive_int, default=300, help="frames of one timed grasp (default 300)")
    p.add_argument("--repeats", type=positive_int, default=5, help="timed grasps per shape (default 5)")
    p.add_argument("--json", action="store_true", help="print the rows as JSON")
    p.set_defaults(func=_bench_judge)


def _bench_judge(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from fv_algos.grasp_judge import GraspJudge
    from fv_algos.slip.models import count_parameters
    from fv_algos.trial_net import MAX_LAYERS, TrialNet
    from nodes.plots import markdown_table
    if max(args.layers) > MAX_LAYERS:
        raise ValueError(f"--layers {max(args.layers)}: at most {MAX_LAYERS} (2**layers frames of context)")
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    series, field_rows = rng.normal(size=(args.frames, 5)), rng.normal(size=(args.frames, 6))
    judges = {(layers, members): GraspJudge(TrialNet(args.hidden, layers, members))
              for layers in args.layers for members in args.members}
    best = dict.fromkeys(judges, float("inf"))
    for _ in range(args.repeats):
        for shape, judge in judges.items():
            judge.reset()
            started = time.perf_counter()
            for k in range(args.frames):
                judge.push(series[k], field_rows[k])
            best[shape] = min(best[shape], (time.perf_counter() - started) / args.frames * 1e3)
    first = best[next(iter(best))]
    rows = [{"layers": layers, "members": members, "hidden": args.hidden, "params": count_parameters(judge.net),
             "memory_frames": 2 * judge.net.radius + 1, "ms_per_frame": round(best[(layers, members)], 4),
             "ratio_to_first": round(best[(layers, members)] / first, 3)}
            for (layers, members), judge in judges.items()]
    print(json.dumps(rows, indent=1) if args.json else markdown_table(rows, list(rows[0])))
    return 0
