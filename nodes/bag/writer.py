"""`BagWriter`: bus messages into MCAP files, split by size or duration, crash-safe.

A bag is a folder ``NAME/`` holding ``NAME_0.mcap``, ``NAME_1.mcap``... (the rosbag2
layout); every file is a complete MCAP on its own, with its schemas, channels, the
recording metadata and the sticky attachments (launch file, calibration). Messages go
into compressed chunks of `chunk_size_b`; `flush()` closes the open chunk and syncs the
file, so a crash loses at most the chunk in progress (`fv bag recover` restores the rest).
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType, Writer

import msgs
from nodes.bag.codec import MESSAGE_ENCODING, META_LATCHED, META_NODE, SCHEMA_ENCODING, join_frames, schema_data

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
DEFAULT_CHUNK_B = 1 << 20
PROFILE = "fv"


def open_mcap(path: Path, compression: str, chunk_size_b: int = DEFAULT_CHUNK_B) -> tuple[IO[bytes], Writer]:
    """A started MCAP writer on a new file `path` (refuses to overwrite), locked while it is open
    (:func:`being_written`)."""
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression {compression!r} is not one of {sorted(COMPRESSIONS)}")
    try:
        stream = open(path, "xb")
    except FileExistsError:
        raise ValueError(f"{path} already exists (not overwritten)") from None
    with contextlib.suppress(OSError):  # a file system without locks: the file is written all the same
        fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    writer = Writer(stream, chunk_size=chunk_size_b, compression=COMPRESSIONS[compression])
    writer.start(profile=PROFILE)
    return stream, writer


def being_written(path: Path) -> bool:
    """Whether an open writer (a recording in progress, a recovery) holds the file `path`: such a file has no
    summary yet, and is neither damaged nor for `fv bag recover` (which took a live recording's file away)."""
    try:
        with open(path, "rb") as f:
            fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    return False


def _size_on_disk(path: Path) -> int:
    """The size of the file ``path``, bytes; 0 when it is not there."""
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def bag_file_index(path: Path) -> int | None:
    """The split index N of ``NAME_N.mcap``, None for other names."""
    match = re.search(r"_(\d+)\.mcap$", path.name)
    return int(match.group(1)) if match else None


@dataclass
class TopicStats:
    """What one topic contributed to a bag."""

    type_name: str
    count: int = 0
    payload_b: int = 0
    first_ns: int = 0
    last_ns: int = 0


@dataclass
class Sticky:
    """An attachment repeated at the start of every split file."""

    name: str
    media_type: str
    data: bytes
    create_ns: int


class BagWriter:
    """Writes raw bus frames into the bag folder `output`.

    max_bag_size_b / max_bag_duration_s: start a new file when the current one reaches
    this many bytes / spans this many seconds of log time (0 = never).
    metadata: {name: {key: value}} records written at the start of every file.
    fsync: `flush()` also forces the file to the disk (survives a power cut).
    """

    def __init__(self, output: Path, *, compression: str = "zstd", chunk_size_b: int = DEFAULT_CHUNK_B,
                 max_bag_size_b: int = 0, max_bag_duration_s: float = 0.0,
                 metadata: dict[str, dict[str, str]] | None = None, fsync: bool = True) -> None:
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression {compression!r} is not one of {sorted(COMPRESSIONS)}")
        self.output = Path(output)
        if self.output.exists():
            raise ValueError(f"bag folder {self.output} already exists (choose another output)")
        self.output.mkdir(parents=True)
        self.compression = compression
        self.chunk_size_b = chunk_size_b
        self.max_bag_size_b = max_bag_size_b
        self.max_bag_duration_ns = int(max_bag_duration_s * 1e9)
        self.metadata = dict(metadata or {})
        self.fsync = fsync
        self.files: list[Path] = []
        self.stats: dict[str, TopicStats] = {}
        self._sticky: dict[str, Sticky] = {}
        self._stream: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str, str, bool], int] = {}
        self._file_start_ns = 0
        self.unfinished: Path | None = None  # a file whose summary and index could not be written (a full disk...)
        self.unflushed: dict[str, int] = {}  # per topic, messages written since the file last took them (flushed)
        self._in_file: dict[str, int] = {}  # per topic, messages written to the open file
        self._open_next()

    # -- files -----------------------------------------------------------------------
    def _open_next(self) -> None:
        path = self.output / f"{self.output.name}_{len(self.files)}.mcap"
        self._stream, self._writer = open_mcap(path, self.compression, self.chunk_size_b)
        self.files.append(path)
        self._in_file = {}
        self._schemas.clear()
        self._channels.clear()
        self._file_start_ns = 0
        for name, data in self.metadata.items():
            self._writer.add_metadata(name, data)
        for att in self._sticky.values():
            self._writer.add_attachment(att.create_ns, time.time_ns(), att.name, att.media_type, att.data)
        self.flush()

    def _finish_file(self) -> None:
        assert self._writer is not None and self._stream is not None
        try:
            self._writer.finish()
            self._stream.flush()
            if self.fsync:
                os.fsync(self._stream.fileno())
        except Exception:  # a full disk, or the MCAP writer's own error: the file stays as flushed, closed
            self.abandon()
            raise
        self.unflushed.clear()
        self._release().close()

    def _release(self) -> IO[bytes]:
        """The open file's stream, no longer the writer's (`is_open` is False)."""
        assert self._stream is not None
        stream, self._writer, self._stream = self._stream, None, None
        return stream

    def _maybe_split(self, log_time_ns: int) -> None:
        assert self._stream is not None
        too_big = self.max_bag_size_b and self._stream.tell() >= self.max_bag_size_b
        too_long = (self.max_bag_duration_ns and self._file_start_ns
                    and log_time_ns - self._file_start_ns >= self.max_bag_duration_ns)
        if too_big or too_long:
            self._finish_file()
            self._open_next()

    # -- content ---------------------------------------------------------------------
    def attach(self, name: str, data: bytes, media_type: str, sticky: bool = True) -> None:
        """Add an attachment now; a sticky one (replacing an earlier one of the same name)
        is also repeated in every later split file."""
        assert self._writer is not None, "writer is closed"
        now = time.time_ns()
        if sticky:
            self._sticky[name] = Sticky(name, media_type, data, now)
        self._writer.add_attachment(now, now, name, media_type, data)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a metadata record to the current file only (e.g. end-of-recording totals)."""
        assert self._writer is not None, "writer is closed"
        self._writer.add_metadata(name, data)

    def _channel(self, topic: str, type_name: str, node: str, latched: bool) -> int:
        key = (topic, type_name, node, latched)
        channel = self._channels.get(key)
        if channel is None:
            assert self._writer is not None
            schema = self._schemas.get(type_name)
            if schema is None:
                schema = self._writer.register_schema(type_name, SCHEMA_ENCODING, schema_data(type_name))
                self._schemas[type_name] = schema
            channel = self._writer.register_channel(
                topic, MESSAGE_ENCODING, schema, {META_NODE: node, META_LATCHED: "true" if latched else "false"})
            self._channels[key] = channel
        return channel

    def write(self, topic: str, node: str, latched: bool, frames: list[Any], log_time_ns: int,
              header: dict[str, Any] | None = None) -> None:
        """Store one message's frames as received: log_time = `log_time_ns` (receive
        time), publish_time = header pub_ns, MCAP sequence = header seq (mod 2**32).
        `header` is the already decoded header frame, decoded here when None."""
        assert self._writer is not None, "writer is closed"
        header = header or msgs.decode_header(frames[0], topic)
        self._maybe_split(log_time_ns)
        if not self._file_start_ns:
            self._file_start_ns = log_time_ns
        payload = join_frames(frames)
        channel = self._channel(topic, header["type"], node, latched)
        self._writer.add_message(channel, log_time_ns, payload, header["pub_ns"], header["seq"] & 0xFFFFFFFF)
        st = self.stats.get(topic)
        if st is None:
            st = self.stats[topic] = TopicStats(header["type"], first_ns=log_time_ns)
        st.count += 1
        st.payload_b += len(payload)
        st.last_ns = log_time_ns
        self.unflushed[topic] = self.unflushed.get(topic, 0) + 1
        self._in_file[topic] = self._in_file.get(topic, 0) + 1

    def flush(self) -> None:
        """Close the chunk in progress and push everything to the file (and the disk
        when `fsync`): what was written survives a crash from here on."""
        if self._writer is None or self._stream is None:
            return
        self._writer.flush()
        if self.fsync:
            os.fsync(self._stream.fileno())
        if os.fstat(self._stream.fileno()).st_nlink == 0:  # its folder deleted: the file was written on, unseen
            self.unflushed = dict(self._in_file)  # every message of the file went with it
            self.abandon()
            raise FileNotFoundError(errno.ENOENT, "removed while being written (its messages went with it)",
                                    str(self.files[-1]))
        self.unflushed.clear()

    @property
    def is_open(self) -> bool:
        """Whether a file is open for writing: False once closed, or when the split into a new file failed."""
        return self._writer is not None

    @property
    def size_b(self) -> int:
        """Bytes written so far over all files that are still there (a folder removed while recording ended the
        closing summary in a FileNotFoundError)."""
        closed = self.files if self._stream is None else self.files[:-1]
        return sum(_size_on_disk(p) for p in closed) + (self._stream.tell() if self._stream is not None else 0)

    def close(self) -> None:
        """Write the summary and index of the last file and close it."""
        if self._writer is not None:
            self._finish_file()

    def take_unflushed(self) -> dict[str, int]:
        """The messages written since the file last took them ({topic: count}; none once it is closed, or split,
        as it should be: those of a file left unfinished), no longer counted in `stats` (whose `count` is then what
        the files took). The file may hold some of them (the chunks written before its summary failed): `fv bag
        recover` tells."""
        taken, self.unflushed = self.unflushed, {}
        for topic, count in taken.items():
            self.stats[topic].count -= count
        return taken

    def abandon(self) -> None:
        """Close the open file as it stands, without its summary and index, after a failure that left it open: it
        is `unfinished` (`fv bag recover` indexes what was flushed)."""
        if self._stream is None:
            return
        self.unfinished = self.files[-1]
        with contextlib.suppress(OSError):  # the buffered tail on a full disk: the file is unfinished either way
            self._release().close()
