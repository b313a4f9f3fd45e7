"""`fv bag recover`: a bag file cut off by a crash, `kill -9` or a power cut, or damaged
inside, becomes a valid, indexed MCAP again.

The default MCAP reader needs the summary at the end of the file, which a cut file
lacks. Recovery reads the file front to back, one record at a time (chunks whole, checked
against their CRC), and copies every readable record (schemas, channels, messages,
attachments, metadata) into a new file. A damaged stretch (a chunk that fails its CRC, bytes
that are no record) is skipped up to the next chunk that reads whole, so one bad chunk costs
that chunk, not the rest of the file; the cut at the end of a crashed recording is the last
stretch. The report names every stretch lost.
"""
from __future__ import annotations

import io
import mmap
import os
import struct
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Iterator

from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import Writer

from fv_algos.atomic_file import write_atomically
from nodes.bag.reader import MCAP_MAGIC, READ_ERRORS, check_magic, summary_crc_matches
from nodes.bag.writer import being_written, open_mcap

BROKEN_SUFFIX = ".broken"
_FRAME = struct.Struct("<BQ")  # a record's opcode and content length (bytes)
_OPCODES = {int(op) for op in Opcode}


@dataclass
class RecoverReport:
    """What a recovery kept and lost (sizes in bytes, times in ns of log time). damaged: the
    [start, end) byte ranges of the source that were skipped, in file order."""

    source: str
    output: str
    messages: int = 0
    chunks: int = 0
    attachments: int = 0
    metadata: int = 0
    lost_b: int = 0
    last_log_time_ns: int = 0
    complete: bool = False
    damaged: list[tuple[int, int]] = field(default_factory=list)
    unplaced_messages: int = 0  # read, but their channel's definition was in a damaged stretch

    def as_dict(self) -> dict:
        return asdict(self)

    def summary_line(self) -> str:
        if self.complete:
            return f"{self.source} was complete ({self.messages} messages): " + (
                "left as it is" if self.source == self.output else f"copied to {self.output}")
        stretches = ", ".join(f"{a}-{b}" for a, b in self.damaged[:5]) + (" ..." if len(self.damaged) > 5 else "")
        unplaced = (f"; {self.unplaced_messages} messages read but left out, their topic's definition lost"
                    if self.unplaced_messages else "")
        lost = (f"lost {self.lost_b} bytes in {len(self.damaged)} damaged or cut stretch(es) at bytes {stretches}"
                if self.damaged else "nothing lost: the file ended at a record's end, without its summary")
        return (f"recovered {self.messages} messages in {self.chunks} chunks, {self.attachments} attachments, "
                f"{self.metadata} metadata into {self.output} (last log time {self.last_log_time_ns} ns); {lost}"
                + unplaced)


class _Copier:
    """Copies records into a new writer, renumbering schemas and channels. A channel whose schema,
    or a message whose channel, was in a damaged stretch waits for it (a complete file's summary
    repeats every schema and channel); what still waits at the end is counted as lost."""

    def __init__(self, writer: Writer, report: RecoverReport) -> None:
        self.writer = writer
        self.report = report
        self.schemas: dict[int, int] = {0: 0}
        self.channels: dict[int, int] = {}
        self.waiting: dict[tuple[type, int], list] = {}  # (Schema or Channel, its id) -> records that need it

    def copy(self, record: object) -> None:
        w, r = self.writer, self.report
        if isinstance(record, Schema):
            if record.id not in self.schemas:
                self.schemas[record.id] = w.register_schema(record.name, record.encoding, record.data)
                self._release(Schema, record.id)
        elif isinstance(record, Channel):
            if record.schema_id not in self.schemas:
                self.waiting.setdefault((Schema, record.schema_id), []).append(record)
            elif record.id not in self.channels:
                self.channels[record.id] = w.register_channel(record.topic, record.message_encoding,
                                                              self.schemas[record.schema_id], record.metadata)
                self._release(Channel, record.id)
        elif isinstance(record, Message):
            if record.channel_id not in self.channels:
                self.waiting.setdefault((Channel, record.channel_id), []).append(record)
                return
            w.add_message(self.channels[record.channel_id], record.log_time, record.data, record.publish_time,
                          record.sequence)
            r.messages += 1
            r.last_log_time_ns = max(r.last_log_time_ns, record.log_time)
        elif isinstance(record, Attachment):
            w.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
            r.attachments += 1
        elif isinstance(record, Metadata):
            w.add_metadata(record.name, record.metadata)
            r.metadata += 1

    def _release(self, kind: type, record_id: int) -> None:
        for record in self.waiting.pop((kind, record_id), []):
            self.copy(record)

    def unplaced(self) -> int:
        """Messages whose channel (or its schema) was never read: lost with a damaged stretch."""
        return sum(isinstance(r, Message) for records in self.waiting.values() for r in records)


def _record_at(data: mmap.mmap, pos: int) -> tuple[object, list, int] | None:
    """(record, the records it holds, its end offset) of the record that starts at byte `pos` of
    `data`, or None when none reads whole there. A chunk holds its schemas, channels and messages
    and must pass its CRC; any other record holds itself."""
    if pos + _FRAME.size > len(data):
        return None
    opcode, length = _FRAME.unpack_from(data, pos)
    end = pos + _FRAME.size + length
    if opcode not in _OPCODES or end > len(data):
        return None
    try:
        record = next(StreamReader(io.BytesIO(data[pos:end]), skip_magic=True, emit_chunks=True,
                                   record_size_limit=None).records)
        contents = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
    except (StopIteration, *READ_ERRORS):
        return None
    return record, contents, end


def _next_chunk(data: mmap.mmap, pos: int) -> tuple[int, tuple[object, list, int] | None]:
    """(offset, :func:`_record_at` there) of the first chunk at or after byte `pos` that reads whole;
    (len(data), None) when none. A false start needs a length that fits the file and a chunk that
    passes its CRC."""
    chunk = bytes([int(Opcode.CHUNK)])
    while (pos := data.find(chunk, pos)) != -1:
        found = _record_at(data, pos)
        if found is not None and isinstance(found[0], Chunk):
            return pos, found
        pos += 1
    return len(data), None


def _readable_records(source: Path, report: RecoverReport) -> Iterator[tuple[object, list]]:
    """(record, the records it holds) for each readable record of `source` up to its footer,
    skipping each damaged stretch to the next chunk that reads whole. Sets report.damaged and
    report.complete (a footer reached with nothing skipped)."""
    with open(source, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        pos = len(MCAP_MAGIC)
        while pos < len(data):
            found = _record_at(data, pos)
            if found is None:
                resume, found = _next_chunk(data, pos + 1)
                report.damaged.append((pos, resume))
                if found is None:
                    return
            record, contents, end = found
            if isinstance(record, Footer):
                if not summary_crc_matches(data, pos):  # its records are copied whole, the summary built anew
                    report.damaged.append((record.summary_start or pos, end))
                report.complete = not report.damaged
                return
            pos = end
            yield record, contents


def _start(output: Path, compression: str, report: RecoverReport, early: list) -> tuple[IO[bytes], _Copier]:
    stream, writer = open_mcap(output, compression)
    copier = _Copier(writer, report)
    for record in early:
        copier.copy(record)
    return stream, copier


def recover(source: Path, output: Path) -> RecoverReport:
    """Copy every complete record of `source` into the new file `output` (chunks
    compressed as the source's first chunk), whole or not at all: a recovery stopped part way (Ctrl-C)
    left a valid, indexed file of the records copied so far, which looked like the whole recovery.
    Returns what was kept and lost."""
    source, output = Path(source), Path(output)
    check_magic(source)
    if being_written(source):  # in place, it took the file away: the recorder wrote on into the `.broken` copy
        raise ValueError(f"{source} is still being written (a recording in progress): recover it, if need be, once "
                         "the recording has ended")
    if output.exists():
        raise ValueError(f"{output} already exists (not overwritten)")
    report = RecoverReport(str(source), str(output))
    write_atomically(output, lambda tmp: _copy_records(source, tmp, report))
    return report


def _copy_records(source: Path, output: Path, report: RecoverReport) -> None:
    """Copy every readable record of `source` into the new file `output`, counting them in `report`."""
    early: list = []  # attachments and metadata before the first chunk, which sets the compression
    stream = copier = None
    try:
        for record, contents in _readable_records(source, report):
            if copier is None:
                if not isinstance(record, Chunk):
                    early += contents
                    continue
                stream, copier = _start(output, record.compression or "none", report, early)
            report.chunks += isinstance(record, Chunk)
            for item in contents:
                copier.copy(item)
        if copier is None:
            stream, copier = _start(output, "zstd", report, early)
        copier.writer.finish()
    finally:
        if stream is not None:
            stream.close()
    report.lost_b = sum(b - a for a, b in report.damaged)
    report.unplaced_messages = copier.unplaced()


def recover_in_place(path: Path) -> RecoverReport:
    """Recover `path` into itself; the original is kept as ``path.broken``. A complete file is left
    as it is (no copy kept)."""
    path = Path(path)
    broken = path.with_name(path.name + BROKEN_SUFFIX)
    tmp = path.with_name(path.name + ".recovering")
    tmp.unlink(missing_ok=True)
    report = recover(path, tmp)
    report.output = str(path)
    if report.complete:  # also a file recovered before, whose original is kept beside it
        tmp.unlink()
        return report
    if broken.exists():
        tmp.unlink()
        raise ValueError(f"{broken} already exists: move it away or pass --output")
    os.replace(path, broken)
    os.replace(tmp, path)
    return report
