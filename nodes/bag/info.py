"""`fv bag info`: what a bag holds, from its summary (fast) or, with gaps, every message."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from nodes.bag.reader import BagReader
from nodes.bus import SeqTracker


def sequence_gaps(bag: BagReader) -> dict[str, int]:
    """Messages missing by sequence number per topic (each publisher counted apart)."""
    trackers: dict[str, SeqTracker] = {t: SeqTracker() for t in bag.topics()}
    for m in bag.messages():
        trackers[m.topic].accept(m.topic, m.node, m.sequence, m.latched)
    return {t: tr.gaps for t, tr in trackers.items()}


def bag_info(path: Path | str, gaps: bool = False) -> dict[str, Any]:
    """Files, size (bytes), duration (s), start / end log times (ns), message and chunk
    counts, compression, per-topic type / count / rate (Hz) / latched / publishing nodes
    (and sequence gaps when `gaps`), attachments and metadata."""
    bag = BagReader(path)
    duration = bag.duration_s
    missing = sequence_gaps(bag) if gaps else {}
    topics = []
    for t in bag.topics().values():
        entry = {"topic": t.topic, "type": t.type_name, "count": t.count,
                 "rate_hz": t.rate_hz,
                 "latched": t.latched, "nodes": t.nodes}
        if gaps:
            entry["gaps"] = missing[t.topic]
        topics.append(entry)
    return {"path": str(bag.path), "files": [str(p) for p in bag.files], "size_b": bag.size_b,
            "duration_s": duration, "start_ns": bag.start_ns, "end_ns": bag.end_ns,
            "messages": bag.message_count, **bag.chunk_stats(), "topics": topics,
            "attachments": _distinct_attachments(bag), "metadata": bag.metadata()}


def _distinct_attachments(bag: BagReader) -> list[dict[str, Any]]:
    """The bag's attachments, each distinct one once (name, media type, size in bytes) with the files that hold it:
    a split recording repeats its sticky ones (the launch file, the calibration) in every file, which `fv bag info`
    listed once per file."""
    out: dict[tuple[str, str, bytes], dict[str, Any]] = {}
    for a in bag.attachments():
        entry = out.setdefault((a.name, a.media_type, a.data), {"name": a.name, "media_type": a.media_type,
                                                                "size_b": len(a.data), "files": []})
        entry["files"].append(str(a.file))
    return list(out.values())


def _when(ns: int) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(ns / 1e9)) + f".{ns % 10**9 // 10**6:03d} ({ns} ns)"


def format_info(info: dict[str, Any]) -> str:
    """The `fv bag info` text, laid out like `ros2 bag info`."""
    ratio = info["uncompressed_b"] / info["compressed_b"] if info["compressed_b"] else 1.0
    lines = [f"Files:        {', '.join(info['files'])}",
             f"Bag size:     {info['size_b'] / 1e6:.2f} MB",
             f"Duration:     {info['duration_s']:.3f} s",
             f"Start:        {_when(info['start_ns']) if info['messages'] else '- (no messages)'}",
             f"End:          {_when(info['end_ns']) if info['messages'] else '-'}",
             f"Messages:     {info['messages']}",
             f"Chunks:       {info['chunks']} ({'/'.join(info['compression']) or '-'}, ratio {ratio:.2f})",
             "Topics:"]
    width = max((len(t["topic"]) for t in info["topics"]), default=0)
    for t in info["topics"]:
        extra = (" latched" if t["latched"] else "") + (f" gaps {t['gaps']}" if "gaps" in t else "")
        lines.append(f"  {t['topic']:<{width}}  {t['type']:<17} {t['count']:>8} msgs {t['rate_hz']:8.2f} Hz"
                     f"  from {','.join(t['nodes'])}{extra}")
    lines.append("Attachments:" + ("" if info["attachments"] else " none"))
    for a in info["attachments"]:
        lines.append(f"  {a['name']} ({a['media_type']}, {a['size_b']} B)"
                     + (f" in {len(a['files'])} files" if len(a["files"]) > 1 else ""))
    lines.append("Metadata:" + ("" if info["metadata"] else " none"))
    for name, data in info["metadata"].items():
        lines.append(f"  {name}:")
        lines += [f"    {k}: {v}" for k, v in data.items()]
    return "\n".join(lines)
