"""`fv bag recover`: a bag file cut off by a crash, `kill -9` or a power cut becomes a
valid, indexed MCAP again.

The default MCAP reader needs the summary at the end of the file, which a cut file
lacks. Recovery reads the file front to back with a non-seeking `StreamReader`, one
record at a time (chunks whole, checked against their CRC), and copies every complete
record (schemas, channels, messages, attachments, metadata) into a new file. It stops
at the first record that is cut or damaged: everything after it is the loss.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO, Iterator

from mcap.records import Attachment, Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import Writer

from nodes.bag.reader import READ_ERRORS, check_magic
from nodes.bag.writer import open_mcap

BROKEN_SUFFIX = ".broken"


@dataclass
class RecoverReport:
    """What a recovery kept and lost (sizes in bytes, times in ns of log time)."""

    source: str
    output: str
    messages: int = 0
    chunks: int = 0
    attachments: int = 0
    metadata: int = 0
    kept_b: int = 0
    lost_b: int = 0
    last_log_time_ns: int = 0
    complete: bool = False
    stopped_at: str = ""

    def as_dict(self) -> dict:
        return asdict(self)

    def summary_line(self) -> str:
        if self.complete:
            return f"{self.source} was complete: {self.messages} messages copied to {self.output}"
        return (f"recovered {self.messages} messages in {self.chunks} chunks, {self.attachments} attachments, "
                f"{self.metadata} metadata into {self.output}; lost the last {self.lost_b} bytes "
                f"(at most one chunk) after log time {self.last_log_time_ns} ns ({self.stopped_at})")


class _Copier:
    """Copies records into a new writer, renumbering schemas and channels."""

    def __init__(self, writer: Writer, report: RecoverReport) -> None:
        self.writer = writer
        self.report = report
        self.schemas: dict[int, int] = {0: 0}
        self.channels: dict[int, int] = {}

    def copy(self, record: object) -> None:
        w, r = self.writer, self.report
        if isinstance(record, Schema):
            if record.id not in self.schemas:
                self.schemas[record.id] = w.register_schema(record.name, record.encoding, record.data)
        elif isinstance(record, Channel):
            if record.id not in self.channels:
                self.channels[record.id] = w.register_channel(record.topic, record.message_encoding,
                                                              self.schemas[record.schema_id], record.metadata)
        elif isinstance(record, Message):
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


def _complete_records(source: Path, report: RecoverReport) -> Iterator[tuple[object, list]]:
    """(record, the records it holds) for each record of `source` up to the cut; a chunk
    holds its schemas, channels and messages (checked against its CRC), any other record
    just itself. Sets report.kept_b / complete / stopped_at as it goes."""
    with open(source, "rb") as f:
        records = StreamReader(f, emit_chunks=True, record_size_limit=source.stat().st_size).records
        while True:
            try:
                record = next(records)
                contents = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
            except StopIteration:
                return
            except READ_ERRORS as exc:  # the cut: a record that ends early or fails its CRC
                report.stopped_at = f"{type(exc).__name__}: {exc}" if str(exc) else f"{type(exc).__name__} (cut)"
                return
            if isinstance(record, Footer):
                report.complete = True
                return
            yield record, contents
            report.kept_b = f.tell()


def _start(output: Path, compression: str, report: RecoverReport, early: list) -> tuple[IO[bytes], _Copier]:
    stream, writer = open_mcap(output, compression)
    copier = _Copier(writer, report)
    for record in early:
        copier.copy(record)
    return stream, copier


def recover(source: Path, output: Path) -> RecoverReport:
    """Copy every complete record of `source` into the new file `output` (chunks
    compressed as the source's first chunk); returns what was kept and lost."""
    source, output = Path(source), Path(output)
    check_magic(source)
    report = RecoverReport(str(source), str(output))
    early: list = []  # attachments and metadata before the first chunk, which sets the compression
    stream = copier = None
    try:
        for record, contents in _complete_records(source, report):
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
    finally:
        if copier is not None:
            copier.writer.finish()
            stream.close()
    report.lost_b = 0 if report.complete else source.stat().st_size - report.kept_b
    return report


def recover_in_place(path: Path) -> RecoverReport:
    """Recover `path` into itself; the original is kept as ``path.broken``."""
    path = Path(path)
    broken = path.with_name(path.name + BROKEN_SUFFIX)
    if broken.exists():
        raise ValueError(f"{broken} already exists: move it away or pass --output")
    tmp = path.with_name(path.name + ".recovering")
    tmp.unlink(missing_ok=True)
    report = recover(path, tmp)
    os.replace(path, broken)
    os.replace(tmp, path)
    report.output = str(path)
    return report
