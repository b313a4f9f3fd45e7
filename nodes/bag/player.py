"""The `bag_play` node (also `fv bag play`): a bag back onto the bus.

Messages go out as recorded, byte for byte (`PublisherSocket.publish_raw`, nothing
re-encoded): header seq, stamp_ns, pub_ns and node are the recorded ones, and the
envelope names the recorded publisher, so subscribers see the original publishers'
sequence numbers (a skipped stretch counts as a gap, a loop as a publisher restart).
Latched topics are sent latched. Remaps (launch `remap`, `--remap a:=b`) rename topics.

Timing follows the recorded log (receive) times scaled by `rate`; `fast` drops the
timing for batch processing, and `sync_topic` adds flow control: after each message
on `sync_on` the player waits until the pipeline answers on `sync_topic` with a
message stamped at or after it, so a slow consumer never loses a frame (several streams,
e.g. one camera per finger: each `sync_on` topic waits for its own answer topic). A frame that a
pipeline node says ends with it unanswered (`msgs.Unanswered` on `unanswered` beside the answer topic:
`/unanswered` for `/slip`, `/left/unanswered` for `/left/slip`) waits no longer.

Before the first message the player waits for the nodes of `start_after` to report (a replay
pipeline's nodes, every subscription made) and until every played volatile topic has
a subscriber.

`as_recorded_by` replays a live session as its pipeline took it. Each node keeps only its latest frame, so
a live run under load drops frames (at the tracker), and a replay of every recorded frame judges frames the
live run did not: every later P(slip) of the grasp differs. Given the recorded topic on which a stage
answered each frame it took (the tracker's `/markers`, which `fv bag record -a` records), only the frames
the live pipeline took are played (`live_frames`; the others counted in `frames_left_out`), with flow
control on that topic unless `sync_topic` names another, so that the replay drops none itself. Of a live
camera's frames before the first answer (the live tracker's reference frame), the `reference_frame` last are
played: the replay's tracker, which counts the frames it sees, takes its reference at the same frame.

A recording made before a recorder got only running publishers' latched messages as it began
(`nodes.latched_cache`; its metadata lacks the entry that says so) may hold an earlier session's,
left on a forwarder that stayed up: `gone_at_start` finds them, and they are not played.
"""
from __future__ import annotations

import collections
import math
import os
import posixpath
import select
import signal
import sys
import termios
import threading
import time
import tty
from dataclasses import dataclass, field
from functools import cached_property

import msgs
from msgs import Image
from nodes.bag.clock import PlayClock
from nodes.bag.codec import LATCHED_ENTRY, RECORDING_META, split_payload
from nodes.bag.reader import BagError, BagMessage, BagReader
from nodes.bus import PublisherSocket, TopicReader
from nodes.node import UNANSWERED_TOPIC, Node, is_plumbing_topic
from nodes.start_gate import StartGate

SUBSCRIBER_POLL_S = 0.02
KEY_POLL_S = 0.2


@dataclass
class BagPlayParams:
    """How to play a bag.

    path: bag folder or .mcap file. rate: speed factor (1 = recorded timing).
    loop: start over at the end. start_offset_s: skip this much of the bag (the last
    latched message of each latched topic before it is still sent first).
    duration_s: play this much of the bag (0 = to the end). topics: recorded topics to
    play ([] = all); each must be in the bag. optional_topics: topics also played when
    the bag has them (e.g. /tracker/reset, recorded only where a gripper sent it).
    fast: as fast as possible, no timing (batch processing).
    start_paused: wait for space/enter (terminal) or SIGUSR1 before the first message.
    wait_for_subscribers: before the first message, wait up to subscriber_timeout_s
    until each played volatile topic has a subscriber. start_after: nodes whose first
    NodeStatus the first message also waits for (a replay pipeline's nodes, so that each
    gets the bag whole), for start_timeout_s at most (then it plays, warned).
    sync_topic: flow control, wait for an answer on this topic after each `sync_on`
    message ("" = off); sync_on: recorded topic that waits ("" = the first Image
    topic). Several streams (one pipeline per finger): a list of sync topics and a list
    of as many recorded topics, paired in order (each `sync_on[i]` message waits for
    `sync_topic[i]`). A message that a pipeline node says it leaves unanswered (`msgs.Unanswered`
    stamped as it, on `unanswered` in the answer topic's namespace: `unanswered_topic`) waits no
    more (counted in `unanswered`). sync_window: messages of one stream allowed in flight unanswered;
    sync_timeout_s: give up waiting for one answer after this long (counted).
    as_recorded_by: play of each stream only the frames the live pipeline took (`live_frames`): the
    recorded topic on which a stage answered them live (e.g. /markers; a list paired with `sync_on` as
    `sync_topic` is; without `sync_on`, each with the one Image topic played in its namespace,
    `camera_answered_on`), also the sync topic when `sync_topic` is "". "" = every frame.
    reference_frame: as_recorded_by, the replay tracker's `reference_frame`: how many of a live camera's
    frames before the first answered one are played (the last ones), so that it takes its reference there.
    keyboard: space/enter on the terminal toggles pause (when stdin is a terminal).
    end_wait_s: without flow control, how long the player waits after the bag's last message before it ends:
    time for the pipeline to judge the last frames (a replay launch ends with its player; a pair replay's
    fusion, stopped with it, had not yet voted the last state of one finger in 2 of 6 runs).
    """

    path: str = ""
    rate: float = 1.0
    loop: bool = False
    start_offset_s: float = 0.0
    duration_s: float = 0.0
    topics: list[str] = field(default_factory=list)
    optional_topics: list[str] = field(default_factory=list)
    fast: bool = False
    start_paused: bool = False
    wait_for_subscribers: bool = True
    subscriber_timeout_s: float = 5.0
    start_after: list[str] = field(default_factory=list)
    start_timeout_s: float = 30.0
    sync_topic: str | list[str] = ""
    sync_on: str | list[str] = ""
    sync_window: int = 1
    sync_timeout_s: float = 2.0
    as_recorded_by: str | list[str] = ""
    reference_frame: int = 1
    keyboard: bool = False
    end_wait_s: float = 0.0

    def __post_init__(self) -> None:
        if not self.path:
            raise ValueError("path: give the bag to play")
        if self.rate <= 0:
            raise ValueError(f"rate {self.rate} must be > 0")
        if min(self.start_offset_s, self.duration_s, self.subscriber_timeout_s, self.start_timeout_s,
               self.end_wait_s) < 0:
            raise ValueError("start_offset_s, duration_s, subscriber_timeout_s, start_timeout_s and end_wait_s must "
                             "be >= 0")
        if self.sync_window < 1 or self.sync_timeout_s <= 0:
            raise ValueError("sync_window must be >= 1 and sync_timeout_s > 0")
        if self.reference_frame < 0:
            raise ValueError(f"reference_frame {self.reference_frame} must be >= 0")
        waiting = topic_list(self.sync_on)
        for name, noun in (("sync_topic", "sync topic"), ("as_recorded_by", "as_recorded_by topic")):
            answers = topic_list(getattr(self, name))
            if len(answers) > 1 and len(waiting) != len(answers) or len(answers) == 1 and len(waiting) > 1:
                raise ValueError(f"sync_on {waiting} and {name} {answers}: give one recorded topic per {noun}, "
                                 f"paired in order (or one {noun} and at most one sync_on)")
            if len(set(answers)) < len(answers):
                raise ValueError(f"{name} {answers}: a topic is named twice")
        if len(set(waiting)) < len(waiting):
            raise ValueError(f"sync_on {waiting}: a topic is named twice")
        # a missing, unfinished or damaged bag, or one without a topic to play, is refused by `fv launch --check`
        known = self.bag.topics()
        missing = [t for t in dict.fromkeys(self.topics + waiting) if t not in known]
        if missing:
            raise BagError(self.path, f"has no topic {', '.join(map(repr, missing))} to play; its topics: "
                                      f"{sorted(known)}")
        unrecorded = [t for t in topic_list(self.as_recorded_by) if t not in known]
        if unrecorded:
            raise BagError(self.path, f"has no topic {', '.join(map(repr, unrecorded))}, which as_recorded_by "
                                      "names: the live pipeline's answers are needed to play the frames it took "
                                      f"(record the session with `fv bag record -a`); its topics: {sorted(known)}")

    @cached_property
    def bag(self) -> BagReader:
        """The bag at `path`, opened once for the check of these params and the play: its files' summaries are
        read as it opens (tens of ms each for a recording of an hour)."""
        return BagReader(self.path)


def message_id(m: BagMessage) -> tuple[str, str, int, int]:
    """(topic, publishing node, seq, log time ns): one recorded message."""
    return m.topic, m.node, m.sequence, m.log_time_ns


def gone_at_start(bag: BagReader, topics: list[str]) -> set[tuple[str, str, int, int]]:
    """The `message_id`s of the latched messages among `topics` that the recorder of a bag made before
    recorders got only running publishers' latched messages (`RECORDING_META` without `LATCHED_ENTRY`)
    got from gone publishers as it began: where the bag begins with a camera's first frame (an `Image`
    of seq 0), those logged before that frame whose publisher started again next (the same topic and
    node, the seq not going on). A recorder started before a session on a forwarder left running got
    the tracker reference an earlier session had left there, and a replay tracked the whole bag against
    it (19 of 56 decisions of a real grasp differed from the live ones)."""
    meta = bag.metadata().get(RECORDING_META)
    known = bag.topics()
    if meta is None or LATCHED_ENTRY in meta:
        return set()
    first = next(bag.messages([t for t in topics if known[t].type_name == Image.TYPE]), None)
    if first is None or first.sequence != 0:
        return set()
    early: dict[tuple[str, str], list[BagMessage]] = {}  # per publisher, its messages before the frame
    gone: set[tuple[str, str, int, int]] = set()
    for m in bag.messages([t for t in topics if known[t].latched]):
        key = (m.topic, m.node)
        if key in early and m.sequence <= early[key][-1].sequence:  # the publisher started again
            gone.update(message_id(g) for g in early.pop(key))
        if m.log_time_ns < first.log_time_ns:
            early.setdefault(key, []).append(m)
        else:  # after the frame: what came before from this publisher was a running one's
            early.pop(key, None)
    return gone


def live_frames(bag: BagReader, images: str, answers: str, reference_frame: int) -> frozenset[int]:
    """The stamps (ns) of the frames of `images` to play as the live pipeline recorded in `bag` took them, from
    its answers on `answers` (a stage's output stamped as each frame it answered: the tracker's /markers) and
    the frames the stage left unanswered on purpose (each camera's frames before the tracker's reference...).
    Where the bag holds the stage's `unanswered` notices (`unanswered_topic`; `fv bag record -a` records them
    only when named), those of `images` say which. Else a video's frames, which carry their number
    (`frame_index`), are taken where answered: a tracker's frames before a pass's reference change nothing
    when left out. A live camera's are numbered by the frames the tracker has seen. In a recording begun
    before the live tracker's reference its first answer is that reference frame: of the frames before it, the
    `reference_frame` last are taken (all, where the bag holds fewer), so that the replay's tracker, of that
    `reference_frame`, takes its reference there too. The live tracker may have missed some of them (it keeps
    only its latest frame): with all of them played, the replay's took its reference at an earlier frame, and
    every state differed. A recording begun after it holds the tracker's reference (`answers`/reference,
    latched) stamped before its first frame (`recorded_before`): its frames before the first answer were
    dropped live, and none is taken (played, the replay's tracker, resuming that reference, tracked and
    answered them, and every later state differed). BagError when `answers` holds no message."""
    answered = frozenset(_stamp_ns(m) for m in bag.messages([answers]))
    if not answered:
        raise BagError(bag.path, f"holds no message on {answers!r} (as_recorded_by): no frame of {images!r} "
                                 "was answered live")
    notices = unanswered_topic(answers)
    if notices in bag.topics():
        noticed = (m.decode() for m in bag.messages([notices]))
        return answered | {n.stamp_ns for n in noticed if n.topic == images}
    first = min(answered)
    first_frame_ns: int | None = None
    before: collections.deque[int] = collections.deque(maxlen=reference_frame)  # a live camera's, the last ones
    for m in bag.messages([images]):
        header = split_payload(m.payload, m.topic)[0]
        first_frame_ns = header["stamp_ns"] if first_frame_ns is None else first_frame_ns
        if header["stamp_ns"] >= first:
            break
        if header["fields"].get("frame_index", -1) < 0:  # a recording made before Images had one: a live camera's
            before.append(header["stamp_ns"])
    if before and recorded_before(bag, f"{answers}/reference", images, first_frame_ns):
        return answered
    return answered | frozenset(before)


def recorded_before(bag: BagReader, reference: str, images: str, first_frame_ns: int) -> bool:
    """Whether `bag` holds a message on `reference` (the tracker's latched reference) stamped before
    `first_frame_ns`, its first frame's on `images`, not an earlier session's (`gone_at_start`): the live
    tracker had its reference when the recording began."""
    if reference not in bag.topics():
        return False
    earlier = gone_at_start(bag, [images, reference])
    return any(_stamp_ns(m) < first_frame_ns for m in bag.messages([reference]) if message_id(m) not in earlier)


def _stamp_ns(m: BagMessage) -> int:
    """The capture stamp (ns) in the header of the recorded message `m`."""
    return split_payload(m.payload, m.topic)[0]["stamp_ns"]


def camera_answered_on(answers: str, images: list[str]) -> str:
    """The one topic of `images` (the Image topics played) in the namespace of `answers` (`/left/markers`:
    `/left/camera/image`; `/markers`: any), whose frames a live stage answered there; ValueError naming them
    where none or several are."""
    namespace = posixpath.dirname(answers).rstrip("/") + "/"
    cameras = [t for t in images if t.startswith(namespace)]
    if len(cameras) != 1:
        raise ValueError(f"as_recorded_by {answers}: {len(cameras) or 'no'} Image topic(s) played in its namespace "
                         f"{namespace!r} ({', '.join(cameras) or 'played: ' + (', '.join(images) or 'none')}), "
                         "whose frames it would choose: give sync_on, the camera topic it answers")
    return cameras[0]


def unanswered_topic(answer_topic: str) -> str:
    """Where the nodes that answer on `answer_topic` say what they leave unanswered: `unanswered` in its
    namespace (`/slip` -> `/unanswered`, `/left/slip` -> `/left/unanswered`)."""
    return posixpath.join(posixpath.dirname(answer_topic), UNANSWERED_TOPIC)


def topic_list(value: str | list[str]) -> list[str]:
    """A topic param as a list: "" -> [], "/a" -> ["/a"], a list as it is."""
    if isinstance(value, str):
        return [value] if value else []
    return list(value)


class BagPlay(Node):
    """Plays `path` once (or forever with `loop`) and stops when done."""

    Params = BagPlayParams

    def setup(self) -> None:
        p = self.params
        self.bag = p.bag
        known = self.bag.topics()  # holding every topic of `topics` and `sync_on` (the params' check)
        waiting = topic_list(p.sync_on)
        absent = [t for t in p.optional_topics if t not in known]
        if absent:
            self.log.info("not in the bag, not played: %s", ", ".join(absent))
        self.recorded_by = topic_list(p.as_recorded_by)
        self.sync_topics = topic_list(p.sync_topic) or self.recorded_by
        present = [t for t in p.optional_topics if t in known and t not in p.topics]
        self.played_topics = p.topics + present if p.topics else self._data_topics(list(known))
        self.out_topic = {t: self.resolve(t) for t in self.played_topics}
        images = [t for t in self.played_topics if known[t].type_name == Image.TYPE]
        if waiting:
            self.sync_on = waiting
        elif self.recorded_by:
            self.sync_on = [camera_answered_on(answers, images) for answers in self.recorded_by]
        else:
            self.sync_on = images[:1]
        self.live = {topic: live_frames(self.bag, topic, answers, p.reference_frame)
                     for topic, answers in zip(self.sync_on, self.recorded_by)}
        self.gone_at_start = gone_at_start(self.bag, self.played_topics)
        if self.gone_at_start:
            self.log.info("not played: %s, latched messages the recorder got as it began from processes that "
                          "their nodes' next ones replaced in the bag (a forwarder left running kept an earlier "
                          "session's)",
                          ", ".join(sorted(f"{t} from {n}" for t, n, _, _ in self.gone_at_start)))
        self.clock = PlayClock(p.rate, paused=p.start_paused)
        self.error: str | None = None
        self.counters.update(played=0, frames=0, sync_timeouts=0, unanswered=0, loops=0)
        if self.live:
            self.counters["frames_left_out"] = 0
        # stream k: the messages on sync_on[k] (with one stream, every message counted), answered on
        # sync_topics[k]; per stream, the stamps of its messages sent and not yet answered
        self._pending: list[collections.deque[int]] = [collections.deque() for _ in self.sync_topics]
        self._sent_stream = {topic: k for k, topic in enumerate(self.sync_on)} if len(self.sync_topics) > 1 else {}
        self._answer_stream = {topic: k for k, topic in enumerate(self.sync_topics)}
        self._pub = PublisherSocket(self.name, self.address, self.ctx)
        self.keep_answering(self._pub)
        for topic in self.played_topics:
            self.announce(self.out_topic[topic], known[topic].type_name)
        self._notice_streams: dict[str, list[int]] = {}  # unanswered topic -> the streams whose answers it concerns
        for k, topic in enumerate(self.sync_topics):
            if unanswered_topic(topic) not in self.sync_topics:
                self._notice_streams.setdefault(unanswered_topic(topic), []).append(k)
        self._sync = (TopicReader(self.sync_topics + sorted(self._notice_streams), self.address, self.ctx)
                      if self.sync_topics else None)
        self.start_gate = StartGate(self, p.start_after, p.start_timeout_s)
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGUSR1, lambda *_: self._toggle_pause())
        if p.keyboard and sys.stdin.isatty():
            threading.Thread(target=self._read_keys, name=f"{self.name}-keys", daemon=True).start()
        self._thread = threading.Thread(target=self._run_play, name=f"{self.name}-play", daemon=True)
        self._thread.start()

    def _data_topics(self, topics: list[str]) -> list[str]:
        """`topics` (every recorded one) without the bus's plumbing (`is_plumbing_topic`: the nodes' param
        requests and states, the `unanswered` notices, which `fv bag record -a` records only since it leaves
        them out: played, a param request would set the replay's node, a notice release a frame early) and those
        the player waits on for the pipeline's answers (the sync topics and their notices) or reads the live
        ones from (`as_recorded_by`): played, the recorded answers would come beside the pipeline's own, a live
        session's /markers recorded with `-a` each frame's twice on the interpolator's input). Name one in
        `topics` to play it."""
        waited_on = set(self.sync_topics) | {unanswered_topic(t) for t in self.sync_topics}
        answers = [t for t in topics if self.resolve(t) in waited_on or t in self.recorded_by]
        if answers:
            self.log.info("not played: %s, on which the pipeline's answers are awaited", ", ".join(answers))
        plumbing = [t for t in topics if t not in answers and is_plumbing_topic(t)]
        if plumbing:
            self.log.info("not played: %s, the bus's plumbing (name a topic to play it)", ", ".join(plumbing))
        return [t for t in topics if t not in answers and t not in plumbing]

    # -- control ----------------------------------------------------------------------
    def _toggle_pause(self) -> None:
        self.log.info("%s", "paused (space/enter or SIGUSR1 resumes)" if self.clock.toggle_pause() else "playing")

    def _read_keys(self) -> None:
        """Space or enter toggles pause; the terminal is put back as it was."""
        fd = sys.stdin.fileno()
        saved = termios.tcgetattr(fd)
        try:
            tty.setcbreak(fd)
            while not self.stopped:
                if select.select([fd], [], [], KEY_POLL_S)[0] and os.read(fd, 1) in (b" ", b"\n", b"\r"):
                    self._toggle_pause()
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, saved)

    # -- playing ----------------------------------------------------------------------
    def _run_play(self) -> None:
        try:
            self._pub.wait_connected(2.0)
            while self.start_gate.waiting() and not self.stopped:
                time.sleep(SUBSCRIBER_POLL_S)
            if self.params.wait_for_subscribers:
                self._wait_for_subscribers()
            if self.clock.paused:
                self.log.info("paused before the first message: space/enter or `kill -USR1 %d` starts", os.getpid())
            started, paused_s = time.monotonic(), self.clock.paused_s
            while not self.stopped:
                if not self._play_once() or not self.params.loop:  # nothing to play: no loop over nothing
                    break
                self.counters["loops"] += 1
            self._await_sync(1)
            if self._sync is None:  # (with flow control the last answers have come)
                self._stop.wait(self.params.end_wait_s)
            paused_s = self.clock.paused_s - paused_s
            self.log.info("%s", self.summary_line(time.monotonic() - started - paused_s, paused_s))
        except BagError as exc:
            self.error = str(exc)
            self.state, self.message = "error", self.error
            self.log.error("%s", exc)
        finally:
            self.stop()

    def _wait_for_subscribers(self) -> None:
        latched = {t for t, info in self.bag.topics().items() if info.latched}
        missing = {self.out_topic[t] for t in self.played_topics if t not in latched}
        deadline = time.monotonic() + self.params.subscriber_timeout_s
        while missing and time.monotonic() < deadline and not self.stopped:
            missing = {t for t in missing if not self._pub.has_subscribers(t)}
            time.sleep(SUBSCRIBER_POLL_S)
        if missing:
            self.warn(f"no subscriber on {sorted(missing)} after {self.params.subscriber_timeout_s} s; playing anyway")

    def _play_once(self) -> bool:
        """One pass over the selected stretch of the bag; False when it holds nothing to play."""
        p = self.params
        start_ns = self.bag.start_ns + int(p.start_offset_s * 1e9)
        end_ns = start_ns + math.ceil(p.duration_s * 1e9) if p.duration_s else None  # >= 1 ns: holds the first message
        latched = [t for t in self.played_topics if self.bag.topics()[t].latched]
        if p.start_offset_s and latched:
            last: dict[tuple[str, str], BagMessage] = {}
            for m in self.bag.messages(latched, end_ns=start_ns):
                if message_id(m) not in self.gone_at_start:
                    last[(m.topic, m.node)] = m
            for m in last.values():
                self._send(m)
        first = True
        for m in self.bag.messages(self.played_topics, start_ns=start_ns, end_ns=end_ns):
            if first:
                self.clock.start(m.log_time_ns)
                first = False
            if not self.clock.wait(None if p.fast else m.log_time_ns, lambda: self.stopped):
                return True
            if message_id(m) not in self.gone_at_start:
                self._send(m)
        if first:
            self.warn(f"nothing to play in {p.path} from {p.start_offset_s} s for topics {self.played_topics}")
        return not first

    def _send(self, m: BagMessage) -> None:
        try:
            header, frames = split_payload(m.payload, m.topic)
        except msgs.MessageError as exc:
            raise BagError(self.params.path, f"message at log time {m.log_time_ns} ns: {exc}") from None
        if m.topic in self.live and header["stamp_ns"] not in self.live[m.topic]:
            self.counters["frames_left_out"] += 1
            return
        self._pub.publish_raw(self.out_topic[m.topic], m.node, m.latched, frames)
        self.counters["played"] += 1
        if self.sync_on and m.topic not in self.sync_on:
            return
        self.counters["frames"] += 1
        if self._sync is not None:
            self._pending[self._sent_stream.get(m.topic, 0)].append(header["stamp_ns"])
            self._await_sync(self.params.sync_window)

    def _await_sync(self, limit: int) -> None:
        """Wait until every synced stream has fewer than `limit` sent messages that lack an answer (`_answered`);
        after sync_timeout_s without one, the oldest of every stream still at `limit` is given up (counted)."""
        if self._sync is None:
            return
        deadline = time.monotonic() + self.params.sync_timeout_s
        while not self.stopped:
            full = [k for k, pending in enumerate(self._pending) if len(pending) >= limit]
            if not full:
                return
            raw = self._sync.recv_raw(max(0.0, deadline - time.monotonic()))
            if raw is None:
                for k in full:
                    self._pending[k].popleft()
                    self.counters["sync_timeouts"] += 1
                    self.warn(f"no answer on {self.sync_topics[k]} within {self.params.sync_timeout_s} s (counted)")
            elif not self._answered(raw[0], msgs.decode_header(raw[3][0], raw[0])["stamp_ns"]):
                continue
            deadline = time.monotonic() + self.params.sync_timeout_s

    def _answered(self, topic: str, stamp_ns: int) -> bool:
        """Take what a message on `topic` stamped `stamp_ns` answers off the sent messages awaiting one: an
        answer on a sync topic answers its stream's messages stamped at or before it; a notice on an unanswered
        topic, the message of that very stamp in the streams answered in its namespace (counted in `unanswered`;
        two cameras' frames may share a stamp). False when none."""
        if topic in self._answer_stream:
            pending = self._pending[self._answer_stream[topic]]
            answered = bool(pending) and pending[0] <= stamp_ns
            while pending and pending[0] <= stamp_ns:
                pending.popleft()
            return answered
        holding = [self._pending[k] for k in self._notice_streams.get(topic, []) if stamp_ns in self._pending[k]]
        for pending in holding:
            pending.remove(stamp_ns)
        self.counters["unanswered"] += len(holding)
        return bool(holding)

    def summary_line(self, elapsed_s: float, paused_s: float) -> str:
        """The closing line; `elapsed_s` is the time spent playing, the `paused_s` seconds paused left out."""
        c = self.counters
        sync = f", sync timeouts {c['sync_timeouts']}" if self._sync is not None else ""
        if self.live:
            sync += f", {c['frames_left_out']} frames the live pipeline did not take left out"
        paused = f" (and {paused_s:.2f} s paused)" if paused_s > 0 else ""
        rate = c["frames"] / max(elapsed_s, 1e-9)
        if not self.sync_on:  # every message counts: "played 201 messages (201 messages)" said it twice
            return f"played {c['played']} messages in {elapsed_s:.2f} s{paused}: {rate:.1f} messages/s{sync}"
        return (f"played {c['played']} messages ({c['frames']} on {', '.join(self.sync_on)}) in {elapsed_s:.2f} "
                f"s{paused}: {rate:.1f} frames/s{sync}")

    def teardown(self) -> None:
        thread = getattr(self, "_thread", None)
        if thread is not None:
            thread.join()
        for sock in (getattr(self, "_sync", None), getattr(self, "_pub", None)):
            if sock is not None:
                sock.close()
