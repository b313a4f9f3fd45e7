"""`fv bag export`: one topic of a bag to a video, PNG frames, CSV or NPZ; any or every topic to an MCAP
file that Foxglove reads (`nodes.bag.foxglove`).

- mp4 (mp4v) / avi (MJPG) / png: `Image` topics; mono8 and rgb8 frames are converted
  to BGR for OpenCV. PNG files are named ``<index>_<stamp_ns>.png``.
- csv: one row per message: log_time_ns, the header fields and every scalar field
  (lists and maps as JSON); array fields are left out (use npz).
- npz: every column of the CSV as an array of length N, plus each array field stacked
  to shape (N, ...) when all messages agree on its shape, else concatenated along axis 0
  with ``<name>_offsets`` (N + 1 row offsets: message i is rows offsets[i]:offsets[i+1]).
- foxglove (an output named ``*.mcap``): the topics chosen, by default every one, as JSON messages
  with JSON Schemas, images as Foxglove's CompressedImage (PNG or JPEG) or RawImage.
"""
from __future__ import annotations

import csv
import json
import re
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from msgs import Image, Message
from msgs.message import HEADER_FIELDS
from nodes.bag.reader import BagError, BagReader

FORMATS = ("mp4", "avi", "png", "csv", "npz", "foxglove")
SUFFIX_FORMATS = {"mcap": "foxglove"}  # output suffixes that are not their format's name
FOURCC = {"mp4": "mp4v", "avi": "MJPG"}


def _bgr(img: Image) -> np.ndarray:
    from fv_algos.visualize import as_bgr
    return as_bgr(img.data, img.encoding)


def cell(value: Any) -> Any:
    """A scalar field's value as one CSV cell or JSON value: a list or map as its JSON text, else as it is."""
    return json.dumps(value) if isinstance(value, (list, dict)) else value


def _row(msg: Message, log_time_ns: int) -> dict[str, Any]:
    row: dict[str, Any] = {"log_time_ns": log_time_ns}
    row.update({name: getattr(msg, name) for name in HEADER_FIELDS})
    row.update({name: cell(value) for name, value in msg.scalar_fields().items()})
    return row


MAX_TIMEBASE = 65_535  # MPEG-4's largest time-base denominator


def video_fps(fps: float) -> float:
    """``fps`` rounded to the most decimals (3 at most) that keep fps * 10**decimals within MAX_TIMEBASE:
    OpenCV writes a rate as that integer over 10**decimals, and its mp4 writer failed to open at a
    measured 97.2568578 fps (97257 / 1000: "timebase not supported by MPEG 4 standard")."""
    for decimals in (3, 2, 1, 0):
        if round(fps * 10**decimals) <= MAX_TIMEBASE:
            return round(fps, decimals)
    return fps


def _video(messages: Iterator[tuple[str, Message, int]], output: Path, fmt: str, fps: float) -> int:
    import cv2
    writer = None
    count = 0
    try:
        for _topic, msg, _t in messages:
            frame = _bgr(msg)
            if writer is None:
                size = (frame.shape[1], frame.shape[0])
                writer = cv2.VideoWriter(str(output), cv2.VideoWriter_fourcc(*FOURCC[fmt]), video_fps(fps), size)
                if not writer.isOpened():
                    raise RuntimeError(f"OpenCV cannot write {fmt} video to {output}")
            elif (frame.shape[1], frame.shape[0]) != size:
                raise ValueError(f"frame {count} is {frame.shape[1]}x{frame.shape[0]} px, "
                                 f"the video {size[0]}x{size[1]} px")
            writer.write(frame)
            count += 1
    finally:
        if writer is not None:
            writer.release()
    return count


PNG_NAME = re.compile(r"\d{6,}_\d+\.png")  # <index>_<stamp_ns>.png


def _png(messages: Iterator[tuple[str, Message, int]], output: Path) -> int:
    """Frames as PNG files in folder ``output``; the frames of an earlier export there are replaced
    (they were kept, and two exports' frames mixed), any other file is left alone."""
    from fv_algos.atomic_file import write_image
    output.mkdir(parents=True, exist_ok=True)
    for earlier in output.iterdir():
        if PNG_NAME.fullmatch(earlier.name) and earlier.is_file():
            earlier.unlink()
    count = 0
    for _topic, msg, _t in messages:
        path = output / f"{count:06d}_{msg.stamp_ns}.png"
        write_image(path, _bgr(msg))
        count += 1
    return count


def _csv(messages: Iterator[tuple[str, Message, int]], output: Path) -> int:
    count = 0
    with open(output, "w", newline="") as f:
        writer = None
        for _topic, msg, t in messages:
            row = _row(msg, t)
            if writer is None:
                writer = csv.DictWriter(f, fieldnames=list(row))
                writer.writeheader()
            writer.writerow(row)
            count += 1
    return count


def _npz(messages: Iterator[tuple[str, Message, int]], output: Path) -> int:
    columns: dict[str, list] = {}
    arrays: dict[str, list[np.ndarray]] = {}
    for _topic, msg, t in messages:
        for name, value in _row(msg, t).items():
            columns.setdefault(name, []).append(value)
        for name in msg.ARRAYS:
            arrays.setdefault(name, []).append(np.asarray(getattr(msg, name)))
    out: dict[str, np.ndarray] = {name: np.asarray(values) for name, values in columns.items()}
    for name, items in arrays.items():
        if len({a.shape for a in items}) == 1:
            out[name] = np.stack(items)
        elif len({a.shape[1:] for a in items}) == 1:
            out[name] = np.concatenate(items)
            out[f"{name}_offsets"] = np.cumsum([0] + [len(a) for a in items])
        else:
            raise ValueError(f"array {name!r} changes shape beyond its first dimension: cannot export it as npz")
    with open(output, "wb") as f:  # a path not ending in .npz would get the suffix added
        np.savez_compressed(f, **out)
    return len(columns.get("log_time_ns", []))


def export_format(fmt: str | None, output: Path) -> str:
    """The export format: `fmt`, else from the output's suffix (none: png, a folder of frames); ValueError
    naming the formats for another."""
    suffix = output.suffix.lstrip(".").lower()
    fmt = fmt or SUFFIX_FORMATS.get(suffix, suffix) or "png"
    if fmt not in FORMATS:
        raise ValueError(f"export format {fmt!r} is not one of {list(FORMATS)} (from --format or the output suffix)")
    return fmt


def export(path: Path | str, topics: str | Sequence[str] | None, output: Path, fmt: str | None = None,
           fps: float = 0.0, images: str = "png") -> tuple[int, Path]:
    """Export `topics` of the bag at `path` to `output`; returns (messages written, output).
    topics: one topic (a name or a list of one); for foxglove any number, None or [] meaning every topic.
    fmt: one of FORMATS (None: `export_format`). fps: video frame rate (0: the topic's recorded mean rate).
    images: foxglove's image kind (`nodes.bag.foxglove.IMAGE_KINDS`)."""
    bag = BagReader(path)
    known = bag.topics()
    chosen = [topics] if isinstance(topics, str) else list(topics or [])
    missing = [topic for topic in chosen if topic not in known]
    if missing:
        raise BagError(path, f"has no topic {', '.join(map(repr, missing))}; topics: {sorted(known)}")
    fmt = export_format(fmt, output)
    if fmt == "foxglove":
        from nodes.bag.foxglove import export_foxglove
        return export_foxglove(bag, chosen or None, output, images), output
    if len(chosen) != 1:
        raise ValueError(f"export to {fmt} takes one --topic, not {len(chosen)}: several topics, or every one, "
                         "go into one file with --format foxglove")
    topic = chosen[0]
    type_name = known[topic].type_name
    if fmt in ("mp4", "avi", "png") and type_name != Image.TYPE:
        raise ValueError(f"{topic} holds {type_name}, not Image: export it as csv or npz")
    messages = bag.read([topic])
    if fmt == "png":
        return _png(messages, output), output  # each frame written whole
    # whole or not at all: an export that fails or is stopped half-way leaves no file, and an earlier one as it was
    from fv_algos.atomic_file import write_atomically
    if fmt in FOURCC:
        rate = fps or known[topic].rate_hz or 30.0
        return write_atomically(output, lambda tmp: _video(messages, tmp, fmt, rate)), output
    return write_atomically(output, lambda tmp: (_csv if fmt == "csv" else _npz)(messages, tmp)), output
