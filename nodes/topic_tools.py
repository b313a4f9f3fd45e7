"""Introspection: `fv topic list | info | echo | hz | bw | delay | pub` and `fv node list`.

Topics and nodes are discovered from the latched `NodeStatus` messages on `/status`:
the forwarder replays each node's latest one to a new subscriber, and each lists the
node's publishes / subscribes. A status older than `STALE_AFTER_S` belongs to a node
that is gone and is ignored; one that cannot be decoded (a malformed latched status published by
hand) is skipped, named on stderr.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from nodes.arg_types import non_negative_float, positive_float, positive_int

if TYPE_CHECKING:
    from nodes.endpoints import BusAddress

STATUS_TOPIC = "/status"
STALE_AFTER_S = 3.0
DISCOVERY_S = 0.3
SMALL_ARRAY = 32


# -- discovery -----------------------------------------------------------------------
def require_forwarder(wait_s: float = DISCOVERY_S, address: BusAddress | None = None) -> None:
    """RuntimeError naming the bus (`address`, default `FV_BUS`'s) when no forwarder answers on it within
    max(``wait_s``, ANSWER_WAIT_S) s: a tool would otherwise wait for messages for good, or report an empty
    list or a rate of 0 Hz as a finding (`fv topic`, `fv node list`, `fv param`, `fv bag record / play`)."""
    from nodes.endpoints import bus_address
    from nodes.forwarder import ANSWER_WAIT_S, ping, silent_forwarder

    address = address or bus_address()
    if ping(address, max(wait_s, ANSWER_WAIT_S)) is None:
        why = (silent_forwarder(address)
               or "no `fv launch` or `fv forwarder` runs on this bus (FV_BUS)")
        raise RuntimeError(f"no forwarder answers on {address.url}: {why}")


def discover(wait_s: float = DISCOVERY_S) -> dict[str, Any]:
    """{node name: its latest NodeStatus} of the nodes alive now (status not stale)."""
    from nodes.bus import TopicReader

    require_forwarder(wait_s)
    found: dict[str, Any] = {}
    deadline = time.monotonic() + wait_s
    with TopicReader([STATUS_TOPIC]) as reader:
        while (remaining := deadline - time.monotonic()) > 0:
            malformed = reader.malformed
            item = reader.recv(remaining)
            if reader.malformed != malformed:
                print(f"fv: skipped a bad status: {reader.last_malformed}", file=sys.stderr)
            if item is not None and item.msg.TYPE == "NodeStatus":
                found[item.msg.node] = item.msg
    now_ns = time.time_ns()
    return {name: st for name, st in sorted(found.items()) if now_ns - st.stamp_ns <= STALE_AFTER_S * 1e9}


@dataclass
class TopicInfo:
    """A topic seen in NodeStatus: its types and the nodes at each end."""

    topic: str
    types: set[str] = field(default_factory=set)
    publishers: list[str] = field(default_factory=list)
    subscribers: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"topic": self.topic, "types": sorted(self.types), "publishers": self.publishers,
                "subscribers": self.subscribers}


def topic_graph(statuses: dict[str, Any]) -> dict[str, TopicInfo]:
    """{topic: TopicInfo} from the nodes' NodeStatus."""
    graph: dict[str, TopicInfo] = {}
    for name, st in statuses.items():
        for ends, attr in ((st.publishes, "publishers"), (st.subscribes, "subscribers")):
            for topic, type_name in ends:
                info = graph.setdefault(topic, TopicInfo(topic))
                if type_name != "*":
                    info.types.add(type_name)
                if name not in getattr(info, attr):
                    getattr(info, attr).append(name)
    return dict(sorted(graph.items()))


def _print_json(obj: Any) -> None:
    """`obj` as JSON, a figure that could not be measured (NaN: fewer than 2 messages) as null."""
    print(json.dumps(_measured(obj), allow_nan=False), flush=True)


def _measured(obj: Any) -> Any:
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _measured(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_measured(v) for v in obj]
    return obj


def _topic_list(args: argparse.Namespace) -> int:
    graph = topic_graph(discover(args.wait))
    if args.json:
        _print_json([info.as_dict() for info in graph.values()])
        return 0
    for info in graph.values():
        types = f" [{', '.join(sorted(info.types)) or '?'}]" if args.show_types else ""
        print(f"{info.topic}{types}")
    return 0


def _topic_info(args: argparse.Namespace) -> int:
    info = topic_graph(discover(args.wait)).get(args.topic)
    if info is None:
        print(f"fv topic info: no running node publishes or subscribes {args.topic!r}", file=sys.stderr)
        return 1
    if args.json:
        _print_json(info.as_dict())
        return 0
    print(f"Type: {', '.join(sorted(info.types)) or '?'}")
    print(f"Publisher count: {len(info.publishers)}" + "".join(f"\n  {n}" for n in info.publishers))
    print(f"Subscription count: {len(info.subscribers)}" + "".join(f"\n  {n}" for n in info.subscribers))
    return 0


def node_list(args: argparse.Namespace) -> int:
    """`fv node list [--json]`: the running nodes with their health (the `node` command
    itself lives in core_commands)."""
    statuses = discover(args.wait)
    rows = [{"name": name, "state": st.state, "message": st.message, "pid": st.pid, "uptime_s": st.uptime_s,
             "rate_hz": st.rate_hz, "drops": st.drops, "gaps": st.gaps, "malformed": st.malformed,
             "errors": st.errors, "cpu_percent": st.cpu_percent, "rss_bytes": st.rss_bytes,
             "counters": st.counters} for name, st in statuses.items()]
    if args.json:
        _print_json(rows)
        return 0
    for r in rows:
        print(f"{r['name']:<20} {r['state']:<5} pid {r['pid']:<7} up {r['uptime_s']:7.1f} s  "
              f"{r['rate_hz']:7.1f} Hz  cpu {r['cpu_percent']:5.1f}%  drops {r['drops']} gaps {r['gaps']} "
              f"malformed {r['malformed']} errors {r['errors']}" + (f"  {r['message']}" if r["message"] else ""))
    return 0


# -- echo ------------------------------------------------------------------------------
def _array_value(arr: np.ndarray, full: bool) -> dict[str, Any]:
    out: dict[str, Any] = {"dtype": arr.dtype.str, "shape": list(arr.shape)}
    if full or arr.size <= SMALL_ARRAY:
        out["data"] = arr.tolist()
    elif arr.size:
        out.update(min=arr.min().item(), max=arr.max().item(), mean=float(arr.mean()))
    return out


def message_dict(topic: str, msg: Any, arrays: str = "summary") -> dict[str, Any]:
    """A message as plain JSON-able values: header, scalar fields and arrays
    (arrays: "summary" = dtype, shape and data when small or stats; "full"; "none")."""
    out: dict[str, Any] = {"topic": topic, "type": msg.TYPE, "seq": msg.seq, "stamp_ns": msg.stamp_ns,
                           "pub_ns": msg.pub_ns, "frame_id": msg.frame_id, "node": msg.node}
    out.update(msg.scalar_fields())
    if arrays != "none":
        for name in msg.ARRAYS:
            out[name] = _array_value(getattr(msg, name), arrays == "full")
    return out


def _echo(args: argparse.Namespace) -> int:
    from nodes.bus import TopicReader

    arrays = "none" if args.no_arr else "full" if args.full_arrays else "summary"
    count = 1 if args.once else args.count
    shown = 0
    require_forwarder()
    with TopicReader([args.topic]) as reader:
        while count is None or shown < count:
            malformed = reader.malformed
            item = reader.recv(args.timeout)
            if (skipped := reader.malformed - malformed) > 0:  # what subscribers drop: said, not skipped silently
                what = "a malformed message" if skipped == 1 else f"{skipped} malformed messages, the last"
                print(f"fv topic echo: skipped {what}: {reader.last_malformed}", file=sys.stderr, flush=True)
            if item is None:
                print(f"fv topic echo: no message on {args.topic} within {args.timeout} s", file=sys.stderr)
                return 1
            d = message_dict(item.topic, item.msg, arrays)
            if args.json:
                _print_json(d)
            else:
                print("\n".join(f"{k}: {json.dumps(v)}" for k, v in d.items()) + "\n---", flush=True)
            shown += 1
    return 0


# -- hz / bw / delay -------------------------------------------------------------------
def _measure(args: argparse.Namespace, on_msg: Callable[[list, dict, int], None],
             report: Callable[[], dict[str, Any]], text: Callable[[dict[str, Any]], str]) -> int:
    """Feed each fresh message on `args.topic` (frames, header, receive time ns) to
    `on_msg`; print `report()` every second, or once after `--duration` s. Each second's report says how
    many messages came in that second (`new_messages`; as text, "no new messages" when none: the
    figures of a topic gone silent are its last messages', as in ROS's `rostopic hz`), as a JSON line
    with `--json`."""
    from msgs import decode_header
    from nodes.bus import TopicReader

    require_forwarder()
    start_ns = time.time_ns()
    end = None if args.duration is None else time.monotonic() + args.duration
    next_print = time.monotonic() + 1.0
    new = 0
    with TopicReader([args.topic]) as reader:
        while end is None or time.monotonic() < end:
            wait = min(next_print, end or next_print) - time.monotonic()
            raw = reader.recv_raw(max(0.0, wait))
            if raw is not None:
                recv_ns = time.time_ns()
                header = decode_header(raw[3][0], args.topic)
                if not (raw[2] and header["pub_ns"] < start_ns):  # a latched replay predates the measurement
                    on_msg(raw[3], header, recv_ns)  # (a bag played keeps its recorded pub_ns: not a replay)
                    new += 1
            if end is None and time.monotonic() >= next_print:
                next_print += 1.0
                second = dict(topic=args.topic, new_messages=new, **report())
                if args.json:
                    _print_json(second)
                else:
                    print(text(second) if new else "no new messages", flush=True)
                new = 0
    result = dict(topic=args.topic, duration_s=args.duration, **report())
    if args.json:
        _print_json(result)
    else:
        print(text(result))
    return 0


def _stats(values: list[float]) -> dict[str, float]:
    if not values:
        return {"mean": math.nan, "min": math.nan, "max": math.nan, "std": math.nan}
    a = np.asarray(values)
    return {"mean": float(a.mean()), "min": float(a.min()), "max": float(a.max()), "std": float(a.std())}


def _shown(value: float, spec: str, unit: str, scale: float = 1.0) -> str:
    """``value / scale`` formatted by ``spec`` with its ``unit``, or "n/a" for a figure without messages (NaN)."""
    return "n/a" if math.isnan(value) else f"{format(value / scale, spec)}{unit}"


def _hz(args: argparse.Namespace) -> int:
    stamps: list[int] = []

    def on_msg(_frames: list, _header: dict, recv_ns: int) -> None:
        stamps.append(recv_ns)
        del stamps[:-args.window - 1]

    def report() -> dict[str, Any]:
        periods = (np.diff(stamps) / 1e9).tolist()
        s = _stats(periods)
        rate = 1.0 / s["mean"] if periods and s["mean"] > 0 else 0.0
        return {"rate_hz": rate, "min_s": s["min"], "max_s": s["max"], "std_s": s["std"], "window": len(periods)}

    return _measure(args, on_msg, report, lambda r: (
        f"average rate: {r['rate_hz']:.3f}\n\tmin: {_shown(r['min_s'], '.3f', 's')} max: {_shown(r['max_s'], '.3f', 's')} "
        f"std dev: {_shown(r['std_s'], '.5f', 's')} window: {r['window']}"))


def _bw(args: argparse.Namespace) -> int:
    samples: list[tuple[int, int]] = []

    def on_msg(frames: list, _header: dict, recv_ns: int) -> None:
        samples.append((recv_ns, sum(len(f) for f in frames)))
        del samples[:-args.window]

    def report() -> dict[str, Any]:
        sizes = [n for _, n in samples]
        span_s = (samples[-1][0] - samples[0][0]) / 1e9 if len(samples) > 1 else 0.0
        rate = sum(sizes[1:]) / span_s if span_s > 0 else 0.0
        s = _stats(sizes)
        return {"bytes_per_s": rate, "mean_bytes": s["mean"], "min_bytes": s["min"], "max_bytes": s["max"],
                "window": len(sizes)}

    return _measure(args, on_msg, report, lambda r: (
        f"{r['bytes_per_s'] / 1e6:.3f} MB/s from {r['window']} messages\n\tMessage size mean: "
        f"{_shown(r['mean_bytes'], '.2f', ' KB', 1e3)} min: {_shown(r['min_bytes'], '.2f', ' KB', 1e3)} "
        f"max: {_shown(r['max_bytes'], '.2f', ' KB', 1e3)}"))


def _delay(args: argparse.Namespace) -> int:
    delays: list[float] = []
    transport: list[float] = []

    def on_msg(_frames: list, header: dict, recv_ns: int) -> None:
        if header["stamp_ns"]:
            delays.append((recv_ns - header["stamp_ns"]) / 1e6)
        transport.append((recv_ns - header["pub_ns"]) / 1e6)
        del delays[:-args.window], transport[:-args.window]

    def report() -> dict[str, Any]:
        d, t = _stats(delays), _stats(transport)
        return {"delay_ms": d["mean"], "delay_min_ms": d["min"], "delay_max_ms": d["max"], "delay_std_ms": d["std"],
                "transport_ms": t["mean"], "transport_max_ms": t["max"], "window": len(transport)}

    return _measure(args, on_msg, report, lambda r: (
        f"average delay (receive - stamp): {_shown(r['delay_ms'], '.3f', ' ms')}\n\tmin: "
        f"{_shown(r['delay_min_ms'], '.3f', ' ms')} max: {_shown(r['delay_max_ms'], '.3f', ' ms')} std dev: "
        f"{_shown(r['delay_std_ms'], '.3f', ' ms')}  transport (receive - publish): "
        f"{_shown(r['transport_ms'], '.3f', ' ms')}  window: {r['window']}"))


# -- pub -------------------------------------------------------------------------------
def build_message(type_name: str, text: str) -> Any:
    """A message of `type_name` from YAML text of its fields ("{probability: 0.9}");
    arrays from nested lists, in the dtype of the field's default. Errors name the field."""
    import dataclasses

    import msgs
    from msgs.message import HEADER_FIELDS
    from msgs.wire import check_message
    from nodes.params import build_params, parse_text

    cls = msgs.message_type(type_name)
    values = parse_text(text) if text.strip() else {}
    if values is None:
        values = {}
    if not isinstance(values, dict):
        raise ValueError(f"{type_name} fields: {text!r} is not a YAML mapping such as '{{field: value}}'")
    by_publisher = set(HEADER_FIELDS) - {"stamp_ns", "frame_id"}
    settable = sorted(f.name for f in dataclasses.fields(cls) if f.name not in by_publisher)
    for name in values:
        if name in by_publisher:
            raise ValueError(f"{type_name}.{name}: set by the publisher, not settable")
        if name not in settable:  # its fields only: the publisher's (seq, pub_ns, node) were listed too
            raise ValueError(f"{type_name}.{name}: no such field; {type_name} has {settable}")
    defaults = {f.name: f.default_factory() for f in dataclasses.fields(cls) if f.name in cls.ARRAYS}
    for name, default in defaults.items():
        if name in values:
            try:
                values[name] = np.asarray(values[name], dtype=default.dtype)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{type_name}.{name}: {values[name]!r:.80} is not an array of {default.dtype}: "
                                 f"{exc}") from None
    values.setdefault("stamp_ns", time.time_ns())
    msg = build_params(cls, values, where=type_name, what="field")
    check_message(msg)  # as subscribers decode it: "SlipState.probability: 2.0 is not in [0, 1]"
    return msg


def _pub(args: argparse.Namespace) -> int:
    from nodes.bus import PublisherSocket

    msg = build_message(args.type, args.values)
    topic = args.topic  # checked by its argument type
    count = 1 if args.once else args.count
    sock = PublisherSocket(f"fv_topic_pub_{os.getpid()}")
    try:
        if not sock.wait_connected(2.0):
            raise RuntimeError(f"no forwarder answers at {sock.address.url} (start `fv forwarder` or `fv launch`)")
        deadline = time.monotonic() + args.wait_matching
        while not args.latched and not sock.has_subscribers(topic) and time.monotonic() < deadline:
            time.sleep(0.01)
        sent = 0
        next_t = time.monotonic()
        while count is None or sent < count:
            if sent:
                msg.stamp_ns = time.time_ns()
            sock.publish(topic, msg, latched=args.latched)
            sent += 1
            print(f"publishing #{sent}: {msg.TYPE} on {topic}", flush=True)
            next_t += 1.0 / args.rate
            if count is None or sent < count:
                time.sleep(max(0.0, next_t - time.monotonic()))
        if args.latched:  # a latched message goes with its publisher (nodes.latched_cache): stay
            print(f"latched: {topic} kept for later subscribers until Ctrl-C", flush=True)
            sock.answer_until(threading.Event())  # answers the forwarder's refreshes until Ctrl-C
    finally:
        sock.close()
    return 0


# -- command line ----------------------------------------------------------------------
def window_size(text: str) -> int:
    """--window: the messages a statistic covers, 2 or more (a rate or a spread needs two; 0 gave 0.0 Hz)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 2:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number >= 2")
    return value


def _topic_name(text: str) -> str:
    """A topic argument, checked as the bus checks it (argparse names the verb and the value)."""
    from nodes.bus import validate_topic
    try:
        return validate_topic(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def register(sub: argparse._SubParsersAction) -> None:
    topic = sub.add_parser("topic", help="inspect and publish topics (list, info, echo, hz, bw, delay, pub)")
    verbs = topic.add_subparsers(dest="verb", required=True, metavar="VERB")

    def verb(name: str, help_text: str, func: Callable, with_topic: bool = True,
             with_json: bool = True) -> argparse.ArgumentParser:
        p = verbs.add_parser(name, help=help_text)
        if with_topic:  # '' (an unset variable) listened to every topic; "slip" was named only by some verbs
            p.add_argument("topic", type=_topic_name, help="topic name, e.g. /slip")
        if with_json:
            p.add_argument("--json", action="store_true", help="machine-readable JSON output")
        p.set_defaults(func=func)
        return p

    for p in (verb("list", "topics of the running nodes", _topic_list, with_topic=False),
              verb("info", "type, publishers and subscribers of a topic", _topic_info)):
        p.add_argument("--wait", type=positive_float, default=DISCOVERY_S, help="seconds to collect node status")
    verbs.choices["list"].add_argument("-t", "--show-types", action="store_true", help="show message types")

    p = verb("echo", "print messages (one JSON object per line with --json)", _echo)
    p.add_argument("--count", "-n", type=positive_int, default=None, help="stop after N messages")
    p.add_argument("--once", action="store_true", help="print one message and exit")
    p.add_argument("--timeout", type=positive_float, default=None, help="exit 1 when no message comes for S seconds")
    p.add_argument("--no-arr", action="store_true", help="leave array fields out")
    p.add_argument("--full-arrays", action="store_true", help="print whole arrays, not a summary")

    for name, help_text, func in (("hz", "message rate (receive times)", _hz),
                                  ("bw", "bandwidth (bytes of header and arrays)", _bw),
                                  ("delay", "delay of receive time after the header stamp_ns", _delay)):
        p = verb(name, help_text, func)
        p.add_argument("--window", "-w", type=window_size, default=10_000, help="messages the statistics cover (>= 2)")
        p.add_argument("--duration", type=positive_float, default=None,
                       help="measure for S seconds, print once and exit (default: print every second)")

    p = verb("pub", "publish a message: fv topic pub /slip SlipState '{probability: 0.9, slip: true}'", _pub,
             with_json=False)
    p.add_argument("type", help="message type, e.g. SlipState")
    p.add_argument("values", nargs="?", default="", help="fields as YAML, e.g. '{slip: true}'")
    p.add_argument("--rate", "-r", type=positive_float, default=1.0, help="messages per second (default 1)")
    p.add_argument("--count", "--times", "-t", type=positive_int, default=None, help="publish N messages, then exit")
    p.add_argument("--once", "-1", action="store_true", help="publish one message and exit (with --latched: stay)")
    p.add_argument("--latched", action="store_true",
                   help="latched: later subscribers get the last message while this command runs (it stays "
                        "after its last message, until Ctrl-C)")
    p.add_argument("--wait-matching", type=non_negative_float, default=1.0,
                   help="seconds to wait for a subscriber before the first message (default 1)")

