"""`fv bag record | play | info | recover | export`: the bag tools (ros2 bag verbs)."""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from nodes.arg_types import non_negative_float, output_file

SIZE_UNITS = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30}


def parse_size(text: str) -> int:
    """Bytes from "1048576", "512K", "100M" or "2G" (binary units)."""
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([KMG]?)i?B?\s*", text, re.IGNORECASE)
    if not match:
        raise argparse.ArgumentTypeError(f"{text!r} is not a size such as 1048576, 512K, 100M, 2G")
    size = int(float(match.group(1)) * SIZE_UNITS[match.group(2).upper()])
    if size == 0 and float(match.group(1)) > 0:  # `-b 0.1` meant 0 bytes, which is "never split"
        raise argparse.ArgumentTypeError(f"{text!r} is less than a byte (a bare number is bytes: 100M is 100 MiB)")
    return size


def register(sub: argparse._SubParsersAction) -> None:
    bag = sub.add_parser("bag", help="record, play, inspect, recover and export MCAP bags")
    verbs = bag.add_subparsers(dest="verb", required=True, metavar="VERB")

    p = verbs.add_parser("record", help="record topics into a bag folder until Ctrl-C")
    p.add_argument("topics", nargs="*", help="topics to record")
    p.add_argument("-a", "--all", action="store_true",
                   help="record every topic but the bus's plumbing (param topics, unanswered notices) not named")
    p.add_argument("-e", "--regex", default="",
                   help="record topics whose name contains a match (the bus's plumbing only when named)")
    p.add_argument("-x", "--exclude-regex", default="", help="leave out topics whose name contains a match")
    p.add_argument("-o", "--output", default="", help="bag folder (default fv_bag_<date>-<time>)")
    p.add_argument("-b", "--max-bag-size", type=parse_size, default=0, metavar="SIZE",
                   help="start a new file at this size (e.g. 500M; 0 = never)")
    p.add_argument("-d", "--max-bag-duration", type=float, default=0.0, metavar="S",
                   help="start a new file after this many seconds (0 = never)")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="zstd", help="chunk compression")
    p.add_argument("--chunk-size", type=parse_size, default="1M", help="chunk size (default 1M)")
    p.add_argument("--flush-period", type=float, default=0.5, metavar="S",
                   help="close and sync the open chunk at least this often (a crash loses the open chunk and "
                        "what waits for the writer)")
    p.add_argument("--attach", action="append", default=[], metavar="FILE", help="store a file (launch file...)")
    p.add_argument("--no-fsync", action="store_true", help="do not force data to the disk at each flush")
    p.add_argument("--name", default="bag_record", help="node name")
    p.set_defaults(func=_record)

    p = verbs.add_parser("play", help="publish a bag with its recorded timing")
    p.add_argument("bag", help="bag folder or .mcap file")
    p.add_argument("-r", "--rate", type=float, default=1.0, help="speed factor (default 1)")
    p.add_argument("-l", "--loop", action="store_true", help="start over at the end")
    p.add_argument("--start-offset", type=float, default=0.0, metavar="S", help="skip the first S seconds")
    p.add_argument("--duration", type=float, default=0.0, metavar="S", help="play only S seconds (0 = all)")
    p.add_argument("--topics", nargs="+", default=[],
                   help="recorded topics to play (default: all but the bus's plumbing, param and unanswered topics, "
                        "and the answers --sync-topic awaits)")
    p.add_argument("--remap", action="append", default=[], metavar="FROM:=TO", help="rename a topic")
    p.add_argument("-p", "--start-paused", action="store_true", help="wait for space/enter or SIGUSR1")
    p.add_argument("--fast", action="store_true", help="as fast as possible (batch processing)")
    p.add_argument("--no-wait-for-subscribers", action="store_true",
                   help="start at once instead of waiting for a subscriber on each topic")
    p.add_argument("--wait-timeout", type=float, default=5.0, metavar="S", help="longest wait for subscribers")
    p.add_argument("--sync-topic", action="append", default=[],
                   help="flow control: wait for this topic to answer each frame (repeat for several streams, "
                        "one per --sync-on)")
    p.add_argument("--sync-on", action="append", default=[],
                   help="recorded topic whose messages wait (default the first Image); repeated, paired in "
                        "order with --sync-topic")
    p.add_argument("--sync-window", type=int, default=1, help="frames of one stream in flight before waiting")
    p.add_argument("--sync-timeout", type=float, default=2.0, metavar="S", help="give up on one answer after S")
    p.add_argument("--as-recorded-by", action="append", default=[], metavar="TOPIC",
                   help="replay a live session as its pipeline took it: play only the frames whose stamps the "
                        "recorded TOPIC answered (the tracker's /markers; a live pipeline under load drops frames, "
                        "and a replay of every frame judges more), synced on TOPIC unless --sync-topic is given; "
                        "repeated, paired in order with --sync-on")
    p.add_argument("--reference-frame", type=int, metavar="N",
                   help="with --as-recorded-by: the replay tracker's reference_frame; of a live camera's frames "
                        "before the first answered one, the N last are played, so that it takes its reference "
                        "at the frame the live tracker took it (default 1, the tracker's)")
    p.add_argument("--name", default="bag_play", help="node name")
    p.set_defaults(func=_play)

    p = verbs.add_parser("info", help="topics, counts, rates, size, attachments and metadata of a bag")
    p.add_argument("bag", help="bag folder or .mcap file")
    p.add_argument("--json", action="store_true", help="JSON output")
    p.add_argument("--gaps", action="store_true", help="also read every message and count sequence gaps")
    p.set_defaults(func=_info)

    p = verbs.add_parser("recover", help="make a bag cut off by a crash valid and indexed again")
    p.add_argument("file", type=Path, help="the damaged .mcap file")
    p.add_argument("-o", "--output", type=output_file,
                   help="where to write (default: in place, the original kept as FILE.broken)")
    p.add_argument("--json", action="store_true", help="JSON report")
    p.set_defaults(func=_recover)

    p = verbs.add_parser(
        "export", help="a topic to video (mp4/avi), PNG frames, CSV or NPZ; topics to an MCAP that Foxglove reads",
        description="Export a topic to video, PNG frames, CSV or NPZ, or topics (by default every one) to an MCAP "
                    "file that Foxglove opens without our fv-msgpack codec (--format foxglove, or an output "
                    "named *.mcap): each message a JSON object (message encoding json) with a JSON Schema "
                    "(jsonschema), at its recorded log time. Image topics become foxglove.CompressedImage "
                    "(--images png, lossless, the default; jpeg, smaller but lossy) or foxglove.RawImage "
                    "(--images raw); every other type fv.<Type> with its fields as recorded (times as "
                    "{sec, nsec}, 1-D arrays as lists, others as {shape, data} with data flat in C order, list and "
                    "map fields as their JSON text), so a Plot panel plots /slip.probability.")
    p.add_argument("bag", help="bag folder or .mcap file")
    p.add_argument("--topic", action="append", default=[],
                   help="recorded topic to export (one for mp4/avi/png/csv/npz; foxglove: repeat for several, "
                        "default every topic)")
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="output: x.mp4 / x.avi (Image), a folder for PNG (Image), x.csv or x.npz (any type), "
                        "x.mcap (foxglove)")
    p.add_argument("--format", choices=["mp4", "avi", "png", "csv", "npz", "foxglove"],
                   help="default: from the output's suffix (.mcap: foxglove; no suffix: png)")
    p.add_argument("--fps", type=non_negative_float, default=0.0,
                   help="video frame rate (default, 0: the recorded rate)")
    p.add_argument("--images", choices=["png", "jpeg", "raw"], default="png",
                   help="foxglove: Image topics as PNG (lossless, default), JPEG (lossy) or raw pixels")
    p.add_argument("--force", action="store_true", help="replace an output that exists")
    p.set_defaults(func=_export)


def _record(args: argparse.Namespace) -> int:
    from nodes.bag.recorder import BagRecord
    from nodes.topic_tools import require_forwarder
    params = {"output": args.output, "topics": args.topics, "all_topics": args.all, "regex": args.regex,
              "exclude_regex": args.exclude_regex, "compression": args.compression,
              "chunk_size_b": args.chunk_size, "flush_period_s": args.flush_period,
              "max_bag_size_b": args.max_bag_size, "max_bag_duration_s": args.max_bag_duration,
              "attach": args.attach, "fsync": not args.no_fsync}
    node = BagRecord(args.name, params)
    require_forwarder()
    node.spin()
    return 1 if node.state == "error" else 0


def _play(args: argparse.Namespace) -> int:
    from nodes.bag.player import BagPlay
    from nodes.core_commands import parse_remaps
    from nodes.topic_tools import require_forwarder
    if args.reference_frame is not None and not args.as_recorded_by:  # it would change nothing, silently
        raise ValueError("--reference-frame acts only with --as-recorded-by")
    params = {"path": args.bag, "rate": args.rate, "loop": args.loop, "start_offset_s": args.start_offset,
              "duration_s": args.duration, "topics": args.topics, "fast": args.fast,
              "start_paused": args.start_paused, "wait_for_subscribers": not args.no_wait_for_subscribers,
              "subscriber_timeout_s": args.wait_timeout, "sync_topic": args.sync_topic, "sync_on": args.sync_on,
              "sync_window": args.sync_window, "sync_timeout_s": args.sync_timeout,
              "as_recorded_by": args.as_recorded_by, "keyboard": True}
    if args.reference_frame is not None:  # else the player's default, the tracker's
        params["reference_frame"] = args.reference_frame
    node = BagPlay(args.name, params, remap=parse_remaps(args.remap))  # its params' check opens the bag (once):
    require_forwarder()  # a bad one is reported before the bus is checked
    node.spin()
    return 1 if getattr(node, "error", None) else 0


def _info(args: argparse.Namespace) -> int:
    from nodes.bag.info import bag_info, format_info
    info = bag_info(args.bag, gaps=args.gaps)
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0


def _recover(args: argparse.Namespace) -> int:
    from nodes.bag.recover import recover_in_place, recover
    report = recover(args.file, args.output) if args.output else recover_in_place(args.file)
    print(json.dumps(report.as_dict(), indent=2) if args.json else report.summary_line())
    return 0


def _export(args: argparse.Namespace) -> int:
    from nodes.bag.export import export
    if (args.output.is_file() or args.output.is_dir() and any(args.output.iterdir())) and not args.force:
        raise ValueError(f"{args.output} exists and is not empty: pass --force to replace what it holds, or "
                         "choose another output")
    count, out = export(args.bag, args.topic, args.output, args.format, args.fps, args.images)
    print(f"exported {count} messages of {', '.join(args.topic) or 'every topic'} to {out}")
    return 0
