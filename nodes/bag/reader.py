"""Read bags from Python: typed messages for notebooks and dataset building.

>>> for topic, msg, log_time_ns in read_bag("run1", topics=["/field", "/slip"]):
...     ...
>>> bag = BagReader("run1")          # a bag folder or one .mcap file
>>> bag.topics()["/camera/image"].count, bag.attachments(), bag.metadata()

Anything that is not a finished MCAP bag written by `fv bag record` raises `BagError`
naming the file and what is wrong (a crashed recording: run `fv bag recover FILE`).
"""
from __future__ import annotations

import json
import mmap
import struct
import zlib
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import IO, Any, Iterator

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import SeekingReader, make_reader
from mcap.records import Channel
from mcap.stream_reader import CRCValidationError
from mcap.summary import Summary
from zstandard import ZstdError

import msgs
from msgs import Message, MessageError
from nodes.bag.codec import MESSAGE_ENCODING, META_LATCHED, META_NODE, RECORDING_END_META, split_payload
from nodes.bag.writer import bag_file_index, being_written

MCAP_MAGIC = b"\x89MCAP0\r\n"
# what the mcap package, zstandard, lz4 (RuntimeError) and struct raise on damaged bytes (OverflowError: a
# length field of garbage)
READ_ERRORS = (McapError, CRCValidationError, ZstdError, struct.error, OSError, ValueError, RuntimeError, OverflowError,
               IndexError, EOFError)
FOOTER = struct.Struct("<BQQQI")  # the footer record: opcode, length, summary start, summary offsets start, summary CRC
_FOOTER_CRC_END = FOOTER.size - 4  # the footer's bytes the summary CRC covers, from its start


def summary_crc_matches(data: mmap.mmap | bytes, footer_pos: int) -> bool:
    """Whether the summary section of an MCAP file (`data`, its bytes), with its footer record at byte
    `footer_pos`, gives the CRC its footer holds (True when the footer holds none: 0). Nothing else checks the
    summary: zeros written into its chunk indexes were read as they were, and a replay of that file stopped
    in a thread's KeyError."""
    _opcode, _length, start, _offsets, crc = FOOTER.unpack_from(data, footer_pos)
    return crc == 0 or zlib.crc32(data[start or footer_pos:footer_pos + _FOOTER_CRC_END]) == crc


class BagError(ValueError):
    """A bag that cannot be read: names the file and what is wrong."""

    def __init__(self, path: Path | str, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"bag {path}: {reason}")


@dataclass
class TopicInfo:
    """One topic of a bag: message type, message count, latched, publishing nodes, and the log times
    (ns) of its first and last message: exact from a finished recording's totals when the bag holds the
    whole recording (not one of its split files), else the bounds of the chunks that hold it."""

    topic: str
    type_name: str
    count: int = 0
    latched: bool = False
    nodes: list[str] = field(default_factory=list)
    first_ns: int = 0
    last_ns: int = 0

    @property
    def rate_hz(self) -> float:
        """Messages per second over the topic's own span (0 for fewer than 2 messages): a camera's frame
        rate, whatever else the bag held before or after it."""
        span_ns = self.last_ns - self.first_ns
        return (self.count - 1) * 1e9 / span_ns if self.count > 1 and span_ns > 0 else 0.0


@dataclass
class BagMessage:
    """One recorded message, undecoded: `payload` is the frames as they were received."""

    topic: str
    node: str
    latched: bool
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    payload: bytes

    def frames(self) -> list[memoryview]:
        """The bus frames [header, arrays...] as views of the payload (no copy)."""
        return split_payload(self.payload, self.topic)[1]

    def decode(self) -> Message:
        """The typed message (arrays are read-only views of the payload)."""
        return msgs.decode(self.frames(), self.topic)


@dataclass
class Attachment:
    """A file stored in a bag (launch file, calibration...)."""

    name: str
    media_type: str
    data: bytes
    log_time_ns: int
    file: Path


def bag_files(path: Path | str) -> list[Path]:
    """The MCAP files of a bag: `path` itself, or the ``*.mcap`` files of a bag folder in
    split order."""
    path = Path(path)
    if path.is_file():
        return [path]
    if not path.exists():
        raise BagError(path, "no such file or folder")
    files = sorted(path.glob("*.mcap"), key=lambda p: (bag_file_index(p) is None, bag_file_index(p) or 0, p.name))
    if not files:
        raise BagError(path, "folder holds no .mcap file")
    return files


def check_magic(path: Path) -> None:
    """BagError unless `path` starts with the MCAP magic."""
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise BagError(path, f"cannot open ({exc.strerror})") from None
    if head != MCAP_MAGIC:
        raise BagError(path, f"not an MCAP file (starts with {head[:8]!r})")


class _SummarisedReader(SeekingReader):
    """A SeekingReader of a file whose summary was read as it was opened (`_File`): the messages, metadata and
    attachments are found through that summary, not a fresh read of it (tens of ms for a recording of an hour,
    its thousands of chunks indexed)."""

    def __init__(self, stream: IO[bytes], summary: Summary, validate_crcs: bool = False) -> None:
        super().__init__(stream, validate_crcs=validate_crcs)
        self._read_summary = summary

    def get_summary(self) -> Summary:
        return self._read_summary


class _File:
    """One MCAP file of a bag with its summary (channels, schemas, statistics, indexes), read once."""

    def __init__(self, path: Path) -> None:
        check_magic(path)
        self.path = path
        self.size_b = path.stat().st_size
        with open(path, "rb") as f:
            try:
                summary = make_reader(f).get_summary()
            except READ_ERRORS as exc:
                _refuse_being_written(path)
                raise BagError(path, f"unfinished or damaged MCAP ({type(exc).__name__}: {str(exc) or 'cut short'}); "
                                     f"a crashed recording? run `fv bag recover {path}`") from None
            if summary is None or summary.statistics is None:
                _refuse_being_written(path)
                raise BagError(path, f"MCAP without summary; run `fv bag recover {path}` to index it")
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
                if not summary_crc_matches(data, self.size_b - len(MCAP_MAGIC) - FOOTER.size):
                    raise BagError(path, f"damaged summary (it does not match its CRC); run `fv bag recover {path}` "
                                         "to index it again")
        self.summary: Summary = summary
        for channel in summary.channels.values():
            if channel.message_encoding != MESSAGE_ENCODING:
                raise BagError(path, f"topic {channel.topic!r} has message encoding {channel.message_encoding!r}, "
                                     f"not {MESSAGE_ENCODING!r} (not recorded by `fv bag record`)")

    def reader(self, stream: IO[bytes], validate_crcs: bool = False) -> SeekingReader:
        """A reader of `stream`, this file opened, through its summary."""
        return _SummarisedReader(stream, self.summary, validate_crcs)

    def messages(self, topics: list[str] | None, start_ns: int | None, end_ns: int | None) -> Iterator[BagMessage]:
        with open(self.path, "rb") as f:
            it = self.reader(f, validate_crcs=True).iter_messages(topics=topics, starting_at=start_ns,
                                                                  ending_before=end_ns, log_time_order=True)
            while True:
                try:
                    _schema, channel, rec = next(it)
                except StopIteration:
                    return
                except READ_ERRORS as exc:
                    raise BagError(self.path, f"damaged data ({type(exc).__name__}: {exc}); "
                                              f"`fv bag recover {self.path}` keeps the readable part") from None
                yield BagMessage(channel.topic, channel.metadata.get(META_NODE, ""),
                                 _latched(channel), rec.log_time, rec.publish_time, rec.sequence, rec.data)


def _refuse_being_written(path: Path) -> None:
    """BagError for a file a recording in progress writes (:func:`nodes.bag.writer.being_written`): it is read once
    the recording ends (its unfinished state had been called a crash, with `fv bag recover` as the advice)."""
    if being_written(path):
        raise BagError(path, "still being written (a recording in progress): it can be read once the recording "
                             "ends; `fv topic echo` shows what is published meanwhile")


@contextmanager
def _damaged_records(path: Path, kind: str) -> Iterator[None]:
    """Read the `kind` records (attachments, metadata) of the file `path` within: one that cannot be read is a
    BagError naming the file (it was the reader's own error, `'utf-8' codec can't decode byte ...`, naming none,
    or a MemoryError for a length of garbage)."""
    try:
        yield
    except (*READ_ERRORS, MemoryError) as exc:
        raise BagError(path, f"cannot read its {kind} ({type(exc).__name__}: {str(exc) or 'a length past any file'}): "
                             f"damaged? `fv bag recover {path}` keeps the readable part") from None


def _latched(channel: Channel) -> bool:
    return channel.metadata.get(META_LATCHED) == "true"


class BagReader:
    """A finished bag (folder of split files, or one .mcap file), checked on opening."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self._files = [_File(p) for p in bag_files(self.path)]

    @property
    def files(self) -> list[Path]:
        return [f.path for f in self._files]

    @property
    def size_b(self) -> int:
        return sum(f.size_b for f in self._files)

    @property
    def message_count(self) -> int:
        return sum(f.summary.statistics.message_count for f in self._files)

    @property
    def start_ns(self) -> int:
        """Log time of the first message (0 for an empty bag)."""
        times = [f.summary.statistics.message_start_time for f in self._files if f.summary.statistics.message_count]
        return min(times, default=0)

    @property
    def end_ns(self) -> int:
        times = [f.summary.statistics.message_end_time for f in self._files if f.summary.statistics.message_count]
        return max(times, default=0)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9

    def chunk_stats(self) -> dict[str, Any]:
        """Chunk count, compressions used and compressed / uncompressed bytes."""
        chunks = [c for f in self._files for c in f.summary.chunk_indexes]
        return {"chunks": len(chunks), "compression": sorted({c.compression or "none" for c in chunks}),
                "compressed_b": sum(c.compressed_size for c in chunks),
                "uncompressed_b": sum(c.uncompressed_size for c in chunks)}

    def topics(self) -> dict[str, TopicInfo]:
        """Topic -> TopicInfo, in order of first appearance: a new dict of new TopicInfos each call, worked out
        once (`_topics`)."""
        return {topic: replace(info, nodes=list(info.nodes)) for topic, info in self._topics.items()}

    @cached_property
    def _topics(self) -> dict[str, TopicInfo]:
        """What `topics` answers, from the files' summaries, read as the bag opens (a file still being written
        has none, and is refused then), and the finished recording's totals, read once: it cannot change for
        this reader. It scans every chunk index per topic: a millisecond or more for a bag of thousands of
        chunks."""
        out: dict[str, TopicInfo] = {}
        for f in self._files:
            counts = f.summary.statistics.channel_message_counts
            for cid, channel in f.summary.channels.items():
                schema = f.summary.schemas.get(channel.schema_id)
                info = out.setdefault(channel.topic, TopicInfo(channel.topic, schema.name if schema else "?"))
                info.count += counts.get(cid, 0)
                info.latched = info.latched or _latched(channel)
                node = channel.metadata.get(META_NODE, "")
                if node not in info.nodes:
                    info.nodes.append(node)
                chunks = [c for c in f.summary.chunk_indexes if cid in c.message_index_offsets]
                if chunks:
                    first, last = min(c.message_start_time for c in chunks), max(c.message_end_time for c in chunks)
                    info.first_ns = min(info.first_ns, first) if info.first_ns else first
                    info.last_ns = max(info.last_ns, last)
        for topic, totals in self._recorded_totals.items():  # the whole recording's: for this bag only when it holds all of it
            if topic in out and "first_ns" in totals and totals["count"] == out[topic].count:  # (one split file
                out[topic].first_ns, out[topic].last_ns = int(totals["first_ns"]), int(totals["last_ns"])  # does not)
        return out

    @cached_property
    def _recorded_totals(self) -> dict[str, dict[str, int]]:
        """Per topic, the finished recording's totals (count, gaps, first_ns, last_ns), read once: {} for a
        bag without them (a recovered one, or recorded before they were kept)."""
        return json.loads(self.metadata().get(RECORDING_END_META, {}).get("per_topic", "{}"))

    def attachments(self) -> list[Attachment]:
        """All attachments of every file (a split bag repeats the sticky ones per file)."""
        out = []
        for f in self._files:
            with open(f.path, "rb") as stream, _damaged_records(f.path, "attachments"):
                for att in f.reader(stream).iter_attachments():
                    out.append(Attachment(att.name, att.media_type, att.data, att.log_time, f.path))
        return out

    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records by name (later files and records override earlier ones)."""
        out: dict[str, dict[str, str]] = {}
        for f in self._files:
            with open(f.path, "rb") as stream, _damaged_records(f.path, "metadata"):
                for rec in f.reader(stream).iter_metadata():
                    out.setdefault(rec.name, {}).update(rec.metadata)
        return out

    def messages(self, topics: list[str] | None = None, start_ns: int | None = None,
                 end_ns: int | None = None) -> Iterator[BagMessage]:
        """Undecoded messages in log-time order; `topics` None = all (one topic may be given as text); log time in
        [start_ns, end_ns). ValueError naming them for bounds that are no whole ns or end before they start (the
        reader's own error blamed the file as damaged; NaN read every message)."""
        for name, bound in (("start_ns", start_ns), ("end_ns", end_ns)):
            if bound is not None and not isinstance(bound, (int, np.integer)):
                raise ValueError(f"{name} {bound!r} is not a whole number of ns")
        if start_ns is not None and end_ns is not None and end_ns < start_ns:
            raise ValueError(f"end_ns {end_ns} is before start_ns {start_ns}")
        topics = [topics] if isinstance(topics, str) else topics  # ("/slip" was read as its letters)
        known = self.topics()
        for topic in topics or ():
            if topic not in known:
                raise BagError(self.path, f"has no topic {topic!r}; topics: {sorted(known)}")
        for f in self._files:
            yield from f.messages(topics, start_ns, end_ns)

    def decoded(self, topics: list[str] | None = None) -> Iterator[tuple[BagMessage, Message]]:
        """(recorded message, its typed message) in log-time order; BagError for one that does not decode."""
        for m in self.messages(topics):
            try:
                msg = m.decode()
            except MessageError as exc:
                raise BagError(self.path, f"message at log time {m.log_time_ns} ns: {exc}") from None
            yield m, msg

    def read(self, topics: list[str] | None = None) -> Iterator[tuple[str, Message, int]]:
        """(topic, typed message, log_time_ns) in log-time order."""
        for m, msg in self.decoded(topics):
            yield m.topic, msg, m.log_time_ns


def read_bag(path: Path | str, topics: list[str] | None = None) -> Iterator[tuple[str, Message, int]]:
    """(topic, typed message, log_time_ns) of every message of the bag at `path`."""
    return BagReader(path).read(topics)
