"""The `bag_record` node (also `fv bag record`): bus topics into an MCAP bag.

Two threads. The receive thread only takes raw frames from the socket (`TopicReader.recv_raw`, nothing
decoded but the small header), stamps each with log_time = the wall time it took it, and hands it to the
writer thread through a `Backlog`; the writer thread stores them with `BagWriter` (compression, chunks) and
every `flush_period_s` closes the open chunk and syncs it. Log times so stay what they were at receipt while
the writer compresses, writes or fsyncs: with one thread, messages waited in the socket meanwhile and were
stamped late (beside two busy loops, up to 540 ms late: README, Bags).

A crash or `kill -9` loses what is not yet flushed: the chunk in progress (at most `flush_period_s` of
messages) and the backlog, as it lost the socket's queue before. The backlog holds at most `queue_depth`
messages, as that queue does: a writer further behind (a disk slower than the stream) drops newly received
messages, counted per topic (counters["dropped"], the summary, the ``fv_recording_end`` record) and warned by
topic name, where the socket dropped them silently. Gaps in seq are counted as messages are received, before the
backlog may drop one: they are the bus's losses only. A writer that fails (a full disk, a split whose new file
cannot be opened) stops the node; the messages received but not stored (those written since the file's last flush,
the one it failed on, those waiting, those received until the stop's drain ends) are counted lost per topic
(counters["lost"], the summary, the node's error, ``fv_recording_end`` where it can still be written). Latched
`CameraInfo` messages are also stored as a YAML attachment ``calibration/<topic>.yaml``; files named in `attach`
(the launch file...) are attached at the start of every split file. On stop the receive queue is drained of the
messages published before the stop, the writer writes all of them, totals go into a ``fv_recording_end`` metadata
record and one summary line is logged.
"""
from __future__ import annotations

import json
import mimetypes
import re
import shlex
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import yaml

import msgs
from msgs import CameraInfo, MessageError
from nodes.bag.backlog import Backlog, Stamped
from nodes.bag.codec import LATCHED_ENTRY, LATCHED_OF_RUNNING, RECORDING_END_META, RECORDING_META
from nodes.bag.writer import COMPRESSIONS, DEFAULT_CHUNK_B, BagWriter
from nodes.bus import ALL_TOPICS, SeqTracker, TopicReader
from nodes.node import Node, is_plumbing_topic

DRAIN_IDLE_S = 0.1  # on stop, keep receiving until the queue stays empty this long, a message published
DRAIN_MAX_S = 2.0   # after the stop comes (a live bus is never quiet), or this long at most
RECV_WAIT_S = 0.1   # the receive thread looks for a stop at least this often


@dataclass
class BagRecordParams:
    """What to record and how.

    output: bag folder ("" = ``fv_bag_YYYYmmdd-HHMMSS`` in the working directory).
    topics / all_topics / regex: record these topics, every topic, or the topics whose
    name contains a match of `regex`; exclude_regex removes matching topics from any of them.
    compression: chunk compression, "zstd", "lz4" or "none". chunk_size_b: chunk size
    in bytes; flush_period_s: the open chunk is closed and synced at least this often.
    max_bag_size_b / max_bag_duration_s: split into a new file at this size / span (0 = off).
    attach: files stored as attachments (launch file, calibration...).
    fsync: force data to the disk at each flush (survives a power cut, not only a crash).
    queue_depth: messages the socket's receive queue holds, and the backlog to the writer thread at most
    (more are dropped, counted and named).
    """

    output: str = ""
    topics: list[str] = field(default_factory=list)
    all_topics: bool = False
    regex: str = ""
    exclude_regex: str = ""
    compression: str = "zstd"
    chunk_size_b: int = DEFAULT_CHUNK_B
    flush_period_s: float = 0.5
    max_bag_size_b: int = 0
    max_bag_duration_s: float = 0.0
    attach: list[str] = field(default_factory=list)
    fsync: bool = True
    queue_depth: int = 10_000

    def __post_init__(self) -> None:
        if not (self.topics or self.all_topics or self.regex):
            raise ValueError("nothing to record: give topics, all_topics (-a) or regex (-e)")
        for name in ("regex", "exclude_regex"):
            try:
                re.compile(getattr(self, name))
            except re.error as exc:
                raise ValueError(f"{name} {getattr(self, name)!r} is not a regular expression: {exc}") from None
        if self.compression not in COMPRESSIONS:
            raise ValueError(f"compression {self.compression!r} is not one of {sorted(COMPRESSIONS)}")
        if self.chunk_size_b <= 0 or self.flush_period_s <= 0 or self.queue_depth <= 0:
            raise ValueError("chunk_size_b, flush_period_s and queue_depth must be > 0")
        if self.max_bag_size_b < 0 or self.max_bag_duration_s < 0:
            raise ValueError("max_bag_size_b and max_bag_duration_s must be >= 0 (0 = no split)")
        for path in self.attach:
            if not Path(path).is_file():
                raise ValueError(f"attach: {path!r} is " + ("a folder, not a file" if Path(path).is_dir()
                                                            else "not found"))


def software_version() -> str:
    try:
        return f"fingervision {version('fingervision')}"
    except PackageNotFoundError:
        return "fingervision (not installed)"


def calibration_yaml(info: CameraInfo, topic: str) -> bytes:
    """A CameraInfo as the YAML calibration attachment (its model, K and D in px)."""
    return yaml.safe_dump({"topic": topic, "frame_id": info.frame_id, "model": info.model, "width": info.width,
                           "height": info.height, "K": info.K.tolist(), "D": info.D.tolist(),
                           "rms_px": info.rms_px}, sort_keys=False).encode()


class BagRecord(Node):
    """Records the selected topics into a bag folder until stopped (SIGINT/SIGTERM): the messages published
    before the stop (`stop_ns`, the wall time stop() was first called)."""

    stop_ns: int | None = None
    error = ""  # the recording's failure, once it failed

    def stop(self) -> None:
        if self.stop_ns is None:
            self.stop_ns = time.time_ns()
        super().stop()

    Params = BagRecordParams

    def setup(self) -> None:
        p = self.params
        self._include = re.compile(p.regex) if p.regex else None
        self._exclude = re.compile(p.exclude_regex) if p.exclude_regex else None
        self._only = {self.resolve(t) for t in p.topics}
        output = Path(p.output or time.strftime("fv_bag_%Y%m%d-%H%M%S"))
        self.writer = BagWriter(output, compression=p.compression, chunk_size_b=p.chunk_size_b,
                                max_bag_size_b=p.max_bag_size_b, max_bag_duration_s=p.max_bag_duration_s,
                                fsync=p.fsync, metadata={RECORDING_META: self._recording_metadata()})
        for path in p.attach:
            media = "application/yaml" if path.endswith((".yaml", ".yml")) else (
                mimetypes.guess_type(path)[0] or "application/octet-stream")
            self.writer.attach(Path(path).name, Path(path).read_bytes(), media)
        self._calibrations: dict[str, bytes] = {}
        self._gaps: dict[str, SeqTracker] = {}  # per topic, the seqs received (the receive thread's; `gaps`)
        self._gaps_lock = threading.Lock()
        wanted = [ALL_TOPICS] if (p.all_topics or p.regex) else sorted(self._only)
        self._reader = TopicReader(wanted, self.address, self.ctx, hwm=p.queue_depth)
        self._backlog = Backlog(p.queue_depth)
        self._receive_thread = threading.Thread(target=self._run_receiving, name=f"{self.name}-receive",
                                                daemon=True)
        self._write_thread = threading.Thread(target=self._run_writing, name=f"{self.name}-write", daemon=True)
        self._receive_thread.start()
        self._write_thread.start()
        self.log.info("recording %s into %s", self._selection(), output)

    def _selection(self) -> str:
        """The topic selection in words, e.g. "/a /b regex '^/cam' except regex 'debug'"."""
        p = self.params
        words = ["(all)"] if p.all_topics else sorted(self._only) + ([f"regex {p.regex!r}"] if p.regex else [])
        return " ".join(words + ([f"except regex {p.exclude_regex!r}"] if p.exclude_regex else []))

    def _recording_metadata(self) -> dict[str, str]:
        """Host, start time, software version, command line, bus, topic selection, and that the latched
        messages it gets as it begins are running publishers' (`nodes.latched_cache`)."""
        now_ns = time.time_ns()
        return {"host": socket.gethostname(), "start_time_ns": str(now_ns),
                "start_time": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(now_ns / 1e9)),
                "software": software_version(), "command_line": shlex.join(sys.argv), "node": self.name,
                "bus": self.address.url, "topics": self._selection(), LATCHED_ENTRY: LATCHED_OF_RUNNING}

    def _selected(self, topic: str) -> bool:
        """Whether `topic` is recorded. The bus's plumbing (`is_plumbing_topic`: the nodes' param topics, as
        ROS's services, and the `unanswered` notices) only when named: `-a` and `-e` recorded every node's
        latched params, the player's among them, so a recording of a replay held more than what was played,
        and its pipeline's `unanswered` notices, which, played with the bag, released a `sync_topic` replay's
        frames before the pipeline answered them."""
        if self._exclude is not None and self._exclude.search(topic):
            return False
        if topic in self._only:
            return True
        if is_plumbing_topic(topic):
            return False
        return (self.params.all_topics
                or bool(self._include is not None and self._include.search(topic)))

    def _receive(self, topic: str, node: str, latched: bool, frames: list[Any], published_by_ns: int | None) -> bool:
        """Stamp one received message and queue it for the writer; False (not queued) when it was published
        after `published_by_ns` (a wall time in ns: the stop, while draining)."""
        log_time_ns = time.time_ns()
        if not self._selected(topic):
            return True
        header = msgs.decode_header(frames[0], topic)
        if published_by_ns is not None and header["pub_ns"] > published_by_ns:
            return False
        with self._gaps_lock:
            self._gaps.setdefault(topic, SeqTracker()).accept(topic, node, header["seq"], latched)
        if not self._backlog.put(Stamped(topic, node, latched, frames, header, log_time_ns)) \
                and not self.error:  # a failed writer's error stays the node's state
            self.warn(f"dropping messages of {topic}: the writer is {self.params.queue_depth} messages behind "
                      f"(queue_depth; {self._backlog.dropped[topic]} dropped so far)", kind=f"dropped {topic}")
        return True

    def _record(self, m: Stamped) -> None:
        """Attach a stamped message's calibration, then write it: the message is stored once this returns, and
        not when it raises."""
        if m.header["type"] == CameraInfo.TYPE:
            self._attach_calibration(m.topic, m.frames)
        self.writer.write(m.topic, m.node, m.latched, m.frames, m.log_time_ns, m.header)

    def _attach_calibration(self, topic: str, frames: list[Any]) -> None:
        try:
            text = calibration_yaml(msgs.decode(frames, topic), topic)
        except MessageError as exc:
            self.warn(f"calibration on {topic} not attached: {exc}")
            return
        if self._calibrations.get(topic) != text:
            self._calibrations[topic] = text
            self.writer.attach(f"calibration/{topic.strip('/').replace('/', '_')}.yaml", text, "application/yaml")

    def _run_receiving(self) -> None:
        """The receive thread: stamp and queue until the stop, drain, then close the socket and the backlog."""
        try:
            while not self.stopped:
                raw = self._reader.recv_raw(RECV_WAIT_S)
                if raw is not None and not self._receive(*raw, published_by_ns=self.stop_ns):
                    break  # the stop came while it waited: a message published after it is not recorded
            # the stop's time, not the time this thread saw it: on a loaded machine one more message came between.
            # Drained after a writer's failure too: what was published before it is counted lost (`Backlog`)
            stopped_ns, drain_until = self.stop_ns or time.time_ns(), time.monotonic() + DRAIN_MAX_S
            while time.monotonic() < drain_until and (raw := self._reader.recv_raw(DRAIN_IDLE_S)) is not None:
                if not self._receive(*raw, published_by_ns=stopped_ns):
                    break
        except Exception as exc:
            self._failed(exc)
        finally:
            self._reader.close()
            self._backlog.close()

    def _run_writing(self) -> None:
        """The writer thread: write what the backlog holds, flush every period; once it is finished (or the
        writing failed: what it did not store is counted lost) and the receive thread has ended, close the bag."""
        period = self.params.flush_period_s
        stamped: Stamped | None = None  # the message being stored, until it is
        try:
            next_flush = time.monotonic() + period
            while not self._backlog.finished:
                stamped = self._backlog.get(max(0.0, next_flush - time.monotonic()))
                if stamped is not None:
                    self._record(stamped)
                    stamped = None
                if time.monotonic() >= next_flush:
                    self.writer.flush()
                    self._update_counters()
                    next_flush = time.monotonic() + period
        except Exception as exc:  # disk full, permissions...: stop the node, keep what was written
            self._failed(exc)  # first: the receive thread warns of no drop once the node's error is set
            self._backlog.abandon(stamped)
        finally:
            self._receive_thread.join()
            self._finish()

    def _failed(self, exc: Exception) -> None:
        """Stop the node for a recording error, named in its status and the log."""
        self.error = f"recording failed: {type(exc).__name__}: {exc}"
        self.state, self.message = "error", self.error
        self.log.error("%s", self.message)
        self.stop()

    def _update_counters(self) -> None:
        self.counters.update(recorded=sum(s.count for s in self.writer.stats.values()), gaps=self.total_gaps,
                             malformed=self._reader.malformed, dropped=self._backlog.total_dropped,
                             lost=self._backlog.total_lost, bytes=self.writer.size_b, files=len(self.writer.files))

    @property
    def gaps(self) -> dict[str, int]:
        """Messages missing by seq per topic: lost on the bus before the recorder received them (its own drops
        are `dropped`)."""
        with self._gaps_lock:
            return {topic: tracker.gaps for topic, tracker in self._gaps.items()}

    @property
    def total_gaps(self) -> int:
        return sum(self.gaps.values())

    def _lost_words(self) -> str:
        """The messages received but not stored because the writing failed, e.g. "; 30 messages received were
        not stored (/a 20, /b 10)", or "" for none."""
        lost = self._backlog.lost
        if not lost:
            return ""
        by_topic = ", ".join(f"{topic} {lost[topic]}" for topic in sorted(lost))
        return f"; {sum(lost.values())} messages received were not stored ({by_topic})"

    def _finish(self) -> None:
        """Close the bag with its totals; a file that cannot be finished (the disk full, the MCAP writer's own
        error: the last, or the one a split closed) is named, with the command that indexes what reached it (none for
        a file removed as it was written: its messages are counted lost). After
        a split whose new file could not be opened (the node's error) there is none open to close. The messages
        received but not stored, the writing having failed, are named in the node's error by topic."""
        stats, gaps = self.writer.stats, self.gaps
        unfinished, why = self.writer.unfinished, f" ({self.error})"
        if self.writer.is_open:
            try:
                self.writer.add_metadata(RECORDING_END_META, {
                    "end_time_ns": str(time.time_ns()), "messages": str(sum(s.count for s in stats.values())),
                    "gaps": str(sum(gaps.values())), "malformed": str(self._reader.malformed),
                    "dropped": json.dumps(self._backlog.dropped), "lost": json.dumps(self._backlog.lost),
                    "per_topic": json.dumps({t: {"count": s.count, "gaps": gaps.get(t, 0), "first_ns": s.first_ns,
                                                 "last_ns": s.last_ns} for t, s in stats.items()})})
                self.writer.close()
            except Exception as exc:  # not BaseException: Ctrl-C still interrupts
                self.writer.abandon()
                unfinished = self.writer.unfinished
                why = (f": {exc.strerror}" if isinstance(exc, OSError) and exc.strerror
                       else f": {type(exc).__name__}: {exc}")
        if unstored := self.writer.take_unflushed():  # written since the last flush of a file left unfinished
            self._backlog.abandon(unstored=unstored)
        if unfinished is not None:
            self.state, self.message = "error", f"could not finish {unfinished}{why}{self._lost_words()}"
            kept = (f"; what was flushed is kept: run `fv bag recover {unfinished}` to index it" if unfinished.exists()
                    else "")  # (removed with its folder as it was written: nothing to recover)
            self.log.error("%s%s", self.message, kept)
        elif self.error:  # a drop warning of the receive thread, as the writer failed, may have come after it
            self.state, self.message = "error", self.error + self._lost_words()
            if self._backlog.lost:
                self.log.error("%s", self.message)
        self._update_counters()
        self.log.info("%s", self.summary_line())

    def summary_line(self) -> str:
        """One line: messages (gaps, drops, losses) per topic, size, duration, files."""
        stats, gaps, dropped, lost = self.writer.stats, self.gaps, self._backlog.dropped, self._backlog.lost
        first = min((s.first_ns for s in stats.values()), default=0)
        last = max((s.last_ns for s in stats.values()), default=0)
        span_s = max((last - first) / 1e9, 1e-9)

        def losses(topic: str) -> str:
            words = [f"{counts[topic]} {word}" for counts, word in ((gaps, "missing"), (dropped, "dropped"),
                                                                      (lost, "lost")) if counts.get(topic)]
            return f" ({', '.join(words)})" if words else ""

        topics = ", ".join(f"{t} {stats[t].count if t in stats else 0}{losses(t)}"
                           for t in sorted(stats.keys() | dropped.keys() | lost.keys()))
        return (f"recorded {sum(s.count for s in stats.values())} messages in {span_s if stats else 0:.1f} s "
                f"to {self.writer.output} ({len(self.writer.files)} file(s), {self.writer.size_b / 1e6:.1f} MB): "
                f"{topics or 'nothing'}; missing by seq {sum(gaps.values())}, malformed {self._reader.malformed}, "
                f"dropped {self._backlog.total_dropped}" + (f", lost {sum(lost.values())}" if lost else ""))

    def teardown(self) -> None:
        if getattr(self, "_write_thread", None) is not None:
            self._write_thread.join()
