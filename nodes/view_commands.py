"""`fv view`: a recorded session as pictures, offline, the way the live `viewer` shows it:
the camera frame with the markers and their displacement arrows, the displacement field
colour map, and the slip probability strip chart below them.

    fv view --bag run1 --out run1.mp4 [--fps 30] [--start 5 --duration 10]
    fv view --bag run1 --out still.png --at 4.2

Each camera frame is drawn with the latest markers, field and slip state whose capture
stamp is at or before the frame's (the markers of a frame carry that frame's stamp).
"""
from __future__ import annotations

import argparse
import bisect
import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

from nodes.arg_types import non_negative_float, output_file, positive_float, positive_int

if TYPE_CHECKING:
    import numpy as np

    from msgs import Image

VIDEO_SUFFIXES = {".mp4": "mp4", ".avi": "avi"}
STILL_SUFFIXES = (".png", ".jpg", ".jpeg")
STAMP_MARGIN_S = 2.0  # extra bag time read around the frames for messages logged late or early
RATE_PROBE_FRAMES = 30  # the video's default frame rate is the capture rate of its first frames
DEFAULT_FPS = 30.0  # for a video of a single frame


@dataclass
class ViewStyle:
    """How the pictures look: panel height in px, slip chart span in s, marker arrow
    length per px of displacement, field colour scale top in px (0 = auto per frame)."""

    height_px: int = 360
    history_s: float = 10.0
    arrow_scale: float = 3.0
    field_range_px: float = 0.0

    def __post_init__(self) -> None:
        if self.height_px < 64:
            raise ValueError(f"height {self.height_px} px is too small (>= 64)")
        if not (self.history_s > 0 and self.arrow_scale > 0 and self.field_range_px >= 0):
            raise ValueError(f"history {self.history_s} s and arrow scale {self.arrow_scale} must be > 0, "
                             f"field range {self.field_range_px} px >= 0")


@dataclass
class ViewTopics:
    """The recorded topics to draw."""

    image: str = "/camera/image"
    markers: str = "/markers"
    field: str = "/field"
    slip: str = "/slip"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="a bag as a video or a still: frame with marker arrows | field colour map, "
                                    "slip probability below")
    p.add_argument("--bag", required=True, help="bag folder or .mcap file")
    p.add_argument("--out", "-o", type=output_file, required=True,
                   help="output: x.mp4 (mp4v) or x.avi (MJPG) video, or x.png / x.jpg still")
    p.add_argument("--fps", type=non_negative_float, default=None,
                   help="video frame rate (default, or 0: the camera's capture rate)")
    p.add_argument("--start", type=non_negative_float, default=None, metavar="S", help="video: skip the first S seconds of the bag")
    p.add_argument("--duration", type=positive_float, default=None, metavar="S",
                   help="video: S seconds of the bag (default: to the end)")
    p.add_argument("--at", type=non_negative_float, default=None, metavar="S", help="still: the frame S seconds into the bag")
    p.add_argument("--height", type=positive_int, default=ViewStyle.height_px, help="height in px of the frame and field panels")
    p.add_argument("--history", type=positive_float, default=ViewStyle.history_s, metavar="S", help="slip chart span in s")
    p.add_argument("--arrow-scale", type=positive_float, default=ViewStyle.arrow_scale,
                   help="marker arrow length per px of displacement")
    p.add_argument("--field-range", type=non_negative_float, default=ViewStyle.field_range_px, metavar="PX",
                   help="top of the field colour scale in px (0 = auto per frame, at least 1 px)")
    for name, default in vars(ViewTopics()).items():
        p.add_argument(f"--{name}-topic", default=default, help=f"recorded topic of the {name} (default {default})")
    p.set_defaults(func=_view)


def _view(args: argparse.Namespace) -> int:
    still = args.out.suffix.lower() in STILL_SUFFIXES
    if still and (args.start is not None or args.duration is not None or args.fps is not None):
        raise ValueError("--start / --duration / --fps are a video's; a still takes --at S")
    if not still and args.at is not None:
        raise ValueError("--at picks a still's frame (--out x.png); a video takes --start S --duration S")
    style = ViewStyle(args.height, args.history, args.arrow_scale, args.field_range)
    topics = ViewTopics(args.image_topic, args.markers_topic, args.field_topic, args.slip_topic)
    if still:
        size = write_still(args.bag, args.out, args.at or 0.0, style, topics)
        print(f"wrote a {size[0]}x{size[1]} px still to {args.out}")
        return 0
    count, size, fps = write_video(args.bag, args.out, style, topics, fps=args.fps or 0.0,
                                   start_s=args.start or 0.0, duration_s=args.duration or 0.0)
    print(f"wrote {count} frames ({size[0]}x{size[1]} px, {fps:.3g} fps) to {args.out}")
    return 0


class _Timeline:
    """The messages of one topic sorted by capture stamp, for "latest at or before"."""

    def __init__(self, messages: list[Any]) -> None:
        self.messages = sorted(messages, key=lambda m: m.stamp_ns)
        self.stamps = [m.stamp_ns for m in self.messages]

    def at(self, stamp_ns: int) -> Any | None:
        i = bisect.bisect_right(self.stamps, stamp_ns)
        return self.messages[i - 1] if i else None

    def between(self, first_ns: int, last_ns: int) -> list[Any]:
        return self.messages[bisect.bisect_left(self.stamps, first_ns):bisect.bisect_right(self.stamps, last_ns)]


class _Session:
    """A bag opened for drawing: its image topic checked, the other topics read in the
    bag-time span [start_ns, end_ns) (plus margins) and sorted by stamp."""

    def __init__(self, bag_path: str | Path, topics: ViewTopics, style: ViewStyle, start_s: float,
                 duration_s: float) -> None:
        from msgs import Image
        from nodes.bag.reader import BagError, BagReader
        self.bag = BagReader(bag_path)
        self.topics, self.style = topics, style
        known = self.bag.topics()
        if topics.image not in known:
            images = sorted(t for t, info in known.items() if info.type_name == Image.TYPE)
            fix = (f"draw one of its images with --image-topic {images[0]} (and that camera's --markers-topic, "
                   "--field-topic, --slip-topic)" if images else
                   f"record one with `fv bag record {topics.image} {topics.markers} {topics.field} {topics.slip}`")
            raise BagError(bag_path, f"has no {topics.image} topic, so nothing to draw on (topics: {sorted(known)}); "
                                     + fix)
        if known[topics.image].type_name != Image.TYPE:
            raise BagError(bag_path, f"{topics.image} holds {known[topics.image].type_name}, not Image")
        length_s = self.bag.duration_s
        if start_s < 0 or start_s > length_s:
            raise ValueError(f"{start_s:g} s is outside the bag (0 to {length_s:.2f} s)")
        self.start_ns = self.bag.start_ns + round(start_s * 1e9)
        self.end_ns = self.start_ns + round(duration_s * 1e9) if duration_s > 0 else self.bag.end_ns + 1
        margin_ns = round(STAMP_MARGIN_S * 1e9)
        self.missing = [t for t in (topics.markers, topics.field, topics.slip) if t not in known]
        present = [t for t in (topics.markers, topics.field, topics.slip) if t in known]
        by_topic: dict[str, list[Any]] = {t: [] for t in present}
        if present:
            first = self.start_ns - round(style.history_s * 1e9) - margin_ns
            for m in self.bag.messages(present, first, self.end_ns + margin_ns):
                by_topic[m.topic].append(m.decode())
        self.timelines = {t: _Timeline(by_topic.get(t, [])) for t in (topics.markers, topics.field, topics.slip)}

    def images(self) -> Iterator[Image]:
        for m in self.bag.messages([self.topics.image], self.start_ns, self.end_ns):
            yield m.decode()

    def compose(self, image: Image) -> np.ndarray:
        """The picture of one frame: (frame + markers | field) over the slip chart, BGR uint8."""
        import numpy as np

        from fv_algos import visualize as viz
        from nodes.viewer import field_picture, frame_picture
        s, t = self.style, self.topics
        h = s.height_px
        ui = max(1.0, h / ViewStyle.height_px)  # text grows with pictures taller than the default
        stamp = image.stamp_ns
        zoom = h / max(image.height, 1)
        frame = frame_picture(image, self.timelines[t.markers].at(stamp), s.arrow_scale, zoom)
        frame = viz.fit(frame, h, round(image.width * zoom) if image.width else h * 4 // 3)
        field_w = round(1.2 * h)  # a square map, its colour bar and labels
        field = self.timelines[t.field].at(stamp)
        if field is None:
            field_panel = viz.notice_panel(self._absent(t.field), h, field_w)
        else:
            field_panel = field_picture(field, s.field_range_px, h, field_w)
        t_s = (stamp - self.bag.start_ns) / 1e9
        top = viz.hstack([viz.titled(frame, f"{t.image}  +  {t.markers}     t = {t_s:.2f} s", ui),
                          viz.titled(field_panel, f"{t.field}  |d| and direction", ui)])
        chart_h = max(120, h * 2 // 5)
        if t.slip in self.missing:
            chart = viz.notice_panel(self._absent(t.slip), chart_h, top.shape[1])
        else:
            history = self.timelines[t.slip].between(stamp - round(s.history_s * 1e9), stamp)
            chart = viz.render_slip_strip(np.array([(m.stamp_ns - stamp) / 1e9 for m in history]),
                                          np.array([m.probability for m in history]),
                                          np.array([m.slip for m in history], bool), width_px=top.shape[1],
                                          height_px=chart_h, window_s=s.history_s,
                                          threshold=history[-1].threshold if history else 0.5, now_s=0.0,
                                          font_scale=ui)
        picture = viz.vstack([top, viz.titled(chart, f"{t.slip}  slip probability", ui)])
        even = np.zeros(((picture.shape[0] + 1) // 2 * 2, (picture.shape[1] + 1) // 2 * 2, 3), np.uint8)
        even[:picture.shape[0], :picture.shape[1]] = picture  # codecs want even sizes
        return even

    def _absent(self, topic: str) -> str:
        return f"no {topic} in the bag" if topic in self.missing else f"no {topic} yet"


def write_still(bag_path: str | Path, out: Path, at_s: float, style: ViewStyle | None = None,
                topics: ViewTopics | None = None) -> tuple[int, int]:
    """Write the picture of the first frame at or after `at_s` seconds into the bag to
    `out` (.png / .jpg); returns its (width, height) in px."""
    from fv_algos.atomic_file import write_image
    topics = topics or ViewTopics()
    session = _Session(bag_path, topics, style or ViewStyle(), at_s, 0.0)
    image = next(session.images(), None)
    if image is None:
        raise ValueError(f"no {topics.image} message at or after {at_s:g} s "
                         f"(the bag is {session.bag.duration_s:.2f} s long)")
    picture = session.compose(image)
    write_image(out, picture)
    return picture.shape[1], picture.shape[0]


def write_video(bag_path: str | Path, out: Path, style: ViewStyle | None = None, topics: ViewTopics | None = None,
                *, fps: float = 0.0, start_s: float = 0.0,
                duration_s: float = 0.0) -> tuple[int, tuple[int, int], float]:
    """Write one picture per camera frame in [start_s, start_s + duration_s) of bag time
    (duration 0: to the end) to the video `out` (.mp4 mp4v / .avi MJPG).

    Returns:
        (frames written, (width, height) in px, frame rate in Hz).
    """
    import cv2

    from nodes.bag.export import FOURCC
    fmt = VIDEO_SUFFIXES.get(out.suffix.lower())
    if fmt is None:
        raise ValueError(f"--out {out}: use .mp4 or .avi for a video, or {', '.join(STILL_SUFFIXES)} for a still")
    topics = topics or ViewTopics()
    session = _Session(bag_path, topics, style or ViewStyle(), start_s, duration_s)
    images = session.images()
    head = list(itertools.islice(images, RATE_PROBE_FRAMES))
    span_ns = head[-1].stamp_ns - head[0].stamp_ns if head else 0
    fps = fps or ((len(head) - 1) * 1e9 / span_ns if span_ns > 0 else DEFAULT_FPS)
    out.parent.mkdir(parents=True, exist_ok=True)
    writer, size, written = None, (0, 0), 0
    try:
        for image in itertools.chain(head, images):
            picture = session.compose(image)
            if writer is None:
                size = (picture.shape[1], picture.shape[0])
                writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*FOURCC[fmt]), fps, size)
                if not writer.isOpened():
                    raise RuntimeError(f"OpenCV has no {FOURCC[fmt]} encoder to write {out} "
                                       f"(try --out {out.with_suffix('.avi' if fmt == 'mp4' else '.mp4')})")
            elif (picture.shape[1], picture.shape[0]) != size:
                picture = cv2.resize(picture, size, interpolation=cv2.INTER_AREA)  # a frame of another size
            writer.write(picture)
            written += 1
    finally:
        if writer is not None:
            writer.release()
    if not written:
        raise ValueError(f"no {topics.image} message in the chosen span of the bag "
                         f"({session.bag.duration_s:.2f} s long)")
    return written, size, fps
