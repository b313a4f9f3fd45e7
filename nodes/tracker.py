"""The `tracker` node: Image -> MarkerArray on `/markers` at camera rate.

The frame number `reference_frame` (frame 0 of a real camera is often stale) becomes the
reference: its markers are published latched on `/markers/reference`. A frame's number is its
`Image.frame_index` where the camera gives one (a video file or image folder), else the frames this
tracker has seen. A source that starts over (a looped video: a frame_index lower than the frame
before's) starts a new grasp: frame `reference_frame` of the new pass is its reference, as for the
first pass, so that every pass is judged as the video is judged once. Any message on
`/tracker/reset` makes the next frame the new reference. A frame of another size than the
reference's (a camera reopened in another mode) is dropped, warned of and counted (`other_size`)
until then: its markers would be matched to positions of another image.

A recording started after the tracker took its reference holds that reference (latched) but not
its frame: replayed from its first frame (taken as the reference), the skin may be deformed there.
With `recorded_reference`, a replay plays the recorded `/markers/reference` on that topic
(`replay.yaml`, `replay_pair.yaml`), and the tracker tracks the first frame on against it when it is
stamped no later than that frame. A recording holds only the reference of a tracker running when
it began (a gone publisher's latched message is not given to a recorder: `nodes.latched_cache`; of a
recording made before, the player leaves an earlier session's out: `nodes.bag.player.gone_at_start`),
so a reference it holds from before its first frame is the one the live tracker tracked that frame
against, also when that frame is the first of a respawned camera, whose seq starts again at 0. A
recording whose first frame is numbered no more than `reference_frame` in its video (frame_index: the
video's first frames, or a loop's next pass) holds the frame the live tracker took its reference
from, and the replay takes its own there: the one recorded before is the previous pass's.

A tracker that restarts (respawned after a crash) while the skin may be deformed must not
take a deformed frame as the reference: with `resume`, it first waits up to
`resume_wait_s` for the latched `/markers/reference` of its previous process (same node
name, same image size, stamped no later than the first frame this process sees; under `fv
launch`, published since the launch started) and goes on tracking against it: its publisher is
gone, and the forwarder gives it to the subscriptions that ask for gone publishers' messages. It
publishes the reference it resumes (the previous process's or the recording's) as it was taken, stamped at
the frame it was taken from: the slip detector goes on with the grasp under way (and a replay's grasp starts
where the live one did), where a copy stamped at this process's first frame started a new grasp. A
reference stamped after that frame belongs to another stream (e.g. the live session a bus still
holds, when a recording of it is replayed), and one from before the launch to an earlier session (a
forwarder left running keeps it): neither is resumed.

Nor is a reference its previous process published before starting a new grasp and being killed before it
took the new grasp's reference: every grasp a tracker starts is said, latched, on its own `markers/grasp_start`
(`msgs.GraspStart`), and its next process (in this launch) starts that grasp as the previous process would have:
after a /tracker/reset (cause "reset") at its first frame, after its source started over (cause "source
restart", a looped video's next pass) at frame `reference_frame` of the pass, or at its first frame when that
is later in the pass. Nor is a reference whose frame came before the camera's source last started over (the
video camera says each pass's start, latched, on `camera/pass_start`): a pass that began while no process of
the tracker ran starts its own grasp, at its frame `reference_frame`. A reset sent while no process of the
tracker runs reaches none (the bus keeps no message that is not latched, and /tracker/reset is not: latched, a
looped replay played its recorded reset once); `nodes.client.reset_grasp(confirm=...)` says so.

The reference a replay's recording holds (`recorded_reference`) does not take the place of the previous
process's: that process took its reference in this replay, or resumed the recording's and published it again."""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from fv_algos.field import MAX_MARKERS
from fv_algos.perception import Perception, PerceptionParams, resumable_reference
from fv_algos.visualize import as_bgr
from msgs import GraspStart, Image, MarkerArray, Message
from msgs.camera import source_started_over
from nodes.client import GRASP_START_TOPIC, PASS_START_TOPIC, RESET_TOPIC
from nodes.node import Node, launch_started_ns

PRESETS = ("paper", "default", "fastest")


@dataclass
class TrackerNodeParams:
    preset: str = "default"  # paper (SimpleBlobDetector + nearest neighbour) | default | fastest
    reference_frame: int = 1  # frames to skip before taking the reference (frame 0 may be stale)
    resume: bool = True  # after a restart, adopt the previous process's latched reference
    resume_wait_s: float = 0.3  # how long to wait for it before taking a new reference
    input_timeout_s: float = 2.0  # warn in NodeStatus after this long without a frame (0 = never)
    recorded_reference: str = ""  # a replay's topic for the reference its recording holds ("" = none; module doc)
    max_markers: int = MAX_MARKERS  # a frame showing more is no reference (noise; the interpolator's default too)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"preset {self.preset!r} is not one of {PRESETS}")
        if self.reference_frame < 0:
            raise ValueError(f"reference_frame {self.reference_frame} must be >= 0")
        if self.max_markers < 3:
            raise ValueError(f"max_markers {self.max_markers} must be >= 3")
        if self.resume_wait_s < 0 or self.input_timeout_s < 0:
            raise ValueError(f"resume_wait_s {self.resume_wait_s} and input_timeout_s {self.input_timeout_s} must be >= 0")


def marker_array(state, image: Image) -> MarkerArray:
    """MarkerArray message of a `fv_algos.tracking.TrackState` for the frame `image`."""
    return MarkerArray(stamp_ns=image.stamp_ns, frame_id=image.frame_id,
                       ref_px=state.reference_px.astype(np.float32), cur_px=state.current_px.astype(np.float32),
                       valid=state.valid.astype(bool), frames_since_seen=state.frames_since_seen.astype(np.int32),
                       width=image.width, height=image.height)


class TrackerNode(Node):
    """Detects and tracks the skin markers in each camera frame (latest frame only)."""

    Params = TrackerNodeParams

    def setup(self) -> None:
        p = self.params
        self.perception = Perception(replace(PerceptionParams.preset(p.preset), max_markers=p.max_markers))
        self.frames_seen = 0
        self.last_index = -1  # the frame_index of the frame before (-1: none, or a live camera's)
        self.take_next = False  # after /tracker/reset: the next frame is the reference, whatever its number
        self.needs_reference = True
        self.started_ns = time.time_ns()
        self.launch_ns = launch_started_ns()  # references published before it are an earlier session's
        self.resume_until = time.monotonic() + (p.resume_wait_s if p.resume else 0.0)
        self.inherited: MarkerArray | None = None
        self.inherited_from = ""  # whose reference `inherited` is, for the log
        self.first_stamp_ns: int | None = None  # stamp of the first frame this process sees
        self.own_grasp = False  # this process took a reference or started a grasp: the previous one's no longer count
        self.previous_start: GraspStart | None = None  # the previous process's last grasp start
        self.pass_start: GraspStart | None = None  # the camera's last pass start (`camera/pass_start`), this launch's
        self.markers_pub = self.publisher("markers", MarkerArray)
        self.reference_pub = self.publisher("markers/reference", MarkerArray, latched=True)
        self.grasp_pub = self.publisher(GRASP_START_TOPIC, GraspStart, latched=True)  # the last grasp started
        self.subscribe("camera/image", Image, self.on_image, depth=1, stale_after_s=p.input_timeout_s or None,
                       answered_by=self.markers_pub)
        self.subscribe(RESET_TOPIC, None, self.on_reset, depth=1)
        if p.resume:  # subscribed before the reference: the previous process's last grasp start comes first
            self.subscribe(GRASP_START_TOPIC, GraspStart, self.on_grasp_started, depth=1, gone=True)
            self.subscribe(PASS_START_TOPIC, GraspStart, self.on_pass_start, depth=1, gone=True)
            self.subscribe("markers/reference", MarkerArray, self.on_reference, depth=1, gone=True)
        if p.recorded_reference:
            self.subscribe(p.recorded_reference, MarkerArray, self.on_recorded_reference, depth=1)
        self.counters.update(references=0, resumed=0, reference_retries=0, other_size=0, source_restarts=0,
                             bad_references=0)

    def teardown(self) -> None:
        """Say so when frames came but none was tracked: a video of 1 frame, or `reference_frame` past
        its end, ended the launch with status 0 and not one decision, without a word."""
        taken = self.counters.get("references", 0) + self.counters.get("resumed", 0)
        if not taken and getattr(self, "frames_seen", 0) > 0:  # (after /tracker/reset: frames were tracked)
            self.log.warning("%d frame(s) came and none was tracked: no reference was taken (reference_frame "
                             "%d)", self.frames_seen, self.params.reference_frame)

    def on_reset(self, msg: Message) -> None:
        """/tracker/reset: a new grasp from the next frame."""
        self.start_grasp(GraspStart(stamp_ns=msg.stamp_ns, frame_id=msg.frame_id, cause="reset"))

    def on_grasp_started(self, msg: GraspStart) -> None:
        """A grasp a previous process of this node started in this launch (`markers/grasp_start`, latched): a
        reference it published before it (before the grasp's reference was taken) is not resumed. One of an
        earlier launch (a forwarder left running keeps it, e.g. the live session's, as its recording is
        replayed) is not this grasp's."""
        if (not self.own_grasp and self.of_previous_process(msg)
                and (self.previous_start is None or msg.pub_ns > self.previous_start.pub_ns)):
            self.previous_start = msg

    def on_pass_start(self, msg: GraspStart) -> None:
        """The camera's source started over (`camera/pass_start`, latched, published in this launch): a reference
        stamped before it is an earlier pass's, also when no process of this tracker saw the pass start."""
        if msg.pub_ns >= self.launch_ns and (self.pass_start is None or msg.stamp_ns > self.pass_start.stamp_ns):
            self.pass_start = msg

    def of_previous_process(self, msg: Message) -> bool:
        """Whether `msg` was published by a previous process of this node in this launch."""
        return msg.node == self.name and self.launch_ns <= msg.pub_ns < self.started_ns

    def drop_ended_reference(self) -> None:
        """Forget the reference to resume when its grasp has ended since it was taken: its previous process
        started another after publishing it (`markers/grasp_start`: a reset, or its source starting over), or
        the camera's source started over after its frame (`camera/pass_start`: a looped video's next pass, come
        while no process of this tracker ran)."""
        old, started, passed = self.inherited, self.previous_start, self.pass_start
        if old is None:
            return
        if started is not None and old.pub_ns < started.pub_ns:
            why = (f"it was published {1e-9 * (started.pub_ns - old.pub_ns):.3f} s before that process started a new "
                   f"grasp ({started.cause})")
        elif passed is not None and old.stamp_ns < passed.stamp_ns:
            why = f"its frame is {1e-9 * (passed.stamp_ns - old.stamp_ns):.3f} s before the camera's source restarted"
        else:
            return
        self.log.info("%s reference is not resumed: %s", self.inherited_from, why)
        self.inherited = None
        self.resume_until = 0.0

    def after_previous_reset(self) -> bool:
        """Whether the newest grasp start before this process's first reference is a /tracker/reset its previous
        process took (then its next frame is the reference, as it would have been): not when the camera's source
        started over since (then frame `reference_frame` of the pass is)."""
        started, passed = self.previous_start, self.pass_start
        return (not self.own_grasp and started is not None and started.cause == "reset"
                and (passed is None or passed.pub_ns < started.pub_ns))

    def start_grasp(self, start: GraspStart) -> None:
        """A new grasp (`new_grasp`), said (latched) on `markers/grasp_start` for this tracker's next process
        (`on_grasp_started`)."""
        self.new_grasp(take_next=start.cause == "reset")
        self.grasp_pub.publish(start)

    def new_grasp(self, take_next: bool = False) -> None:
        """Take a new reference (neither the previous process's nor the recording's) at frame
        `reference_frame` of the stream, or with `take_next` (after /tracker/reset) at the next frame."""
        self.needs_reference = True
        self.resume_until = 0.0
        self.inherited = None
        self.own_grasp = True
        self.take_next = take_next

    def frame_number(self, msg: Image) -> int:
        """The number of `msg` in its camera's stream (0 first): its frame_index when the camera gives one,
        else the frames this process has seen before it."""
        return msg.frame_index if msg.frame_index >= 0 else self.frames_seen - 1

    def on_reference(self, msg: MarkerArray) -> None:
        """Keep the reference a previous process of this node published (latched), in this launch."""
        if (self.needs_reference and not self.own_grasp and self.of_previous_process(msg)
                and self.resumable(msg, "the previous process's")):
            self.inherited, self.inherited_from = msg, "the previous process's"

    def resumable(self, msg: MarkerArray, whose: str) -> bool:
        """Whether the reference `msg` (`whose`, for the warning) can be tracked against
        (`fv_algos.perception.resumable_reference`); False, warned and counted in bad_references, for one that
        cannot (a NaN marker, fewer than 3, one listed twice): kept, it made every frame fail, and the tracker
        never took a reference of its own."""
        try:
            resumable_reference(msg.ref_px)
        except ValueError as exc:
            self.counters["bad_references"] += 1
            self.warn(f"{whose} reference (from {msg.node!r}) is not used: {exc} (bad_references)",
                      kind="bad reference")
            return False
        return True

    def on_recorded_reference(self, msg: MarkerArray) -> None:
        """Keep the reference a replayed recording holds when it is stamped no later than the first frame
        (frames and references may be taken in either order): the recording began after the live tracker
        took it, and is tracked against it as live. Stamped later, it belongs to a frame of the
        recording, which this tracker takes itself. Not in place of the previous process's: that process took
        its reference in this replay (or resumed the recording's and published it again)."""
        if (self.needs_reference and self.inherited_from != "the previous process's"
                and (self.first_stamp_ns is None or msg.stamp_ns <= self.first_stamp_ns)
                and self.resumable(msg, "the recording's")):
            self.inherited, self.inherited_from = msg, "the recording's"

    def on_image(self, msg: Image) -> None:
        """Track the frame's markers against the reference (mono8, bgr8 or rgb8, read as BGR) and publish them;
        without a reference, take one: the previous process's or the recording's when it can be resumed on
        this frame, else this frame's (at `reference_frame`, or the next after /tracker/reset). A frame with
        no reference in it is a reference_retries warning, and the next frame is tried."""
        self.frames_seen += 1
        image = as_bgr(msg.data, msg.encoding) if msg.encoding == "rgb8" else msg.data  # perception reads BGR
        if source_started_over(msg.frame_index, self.last_index):  # a looped video's next pass
            if not self.counters["source_restarts"]:
                self.log.info("the camera's source started over (frame %d after frame %d): a new grasp, its "
                              "reference at frame %d (reference_frame); each restart counted in source_restarts",
                              msg.frame_index, self.last_index, self.params.reference_frame)
            self.counters["source_restarts"] += 1
            self.start_grasp(GraspStart(stamp_ns=msg.stamp_ns, frame_id=msg.frame_id, cause="source restart"))
        self.last_index = msg.frame_index
        if self.first_stamp_ns is None:
            self.first_stamp_ns = msg.stamp_ns
            if (0 <= msg.frame_index <= self.params.reference_frame and self.inherited is not None
                    and self.inherited_from == "the recording's"):
                self.log.info("the recording starts at frame %d of its video, so the live tracker took its "
                              "reference within it: the reference recorded before it (stamped %.1f s before the "
                              "first frame, the previous pass's) is not used", msg.frame_index,
                              1e-9 * (msg.stamp_ns - self.inherited.stamp_ns))
                self.inherited = None
        if self.needs_reference:
            self.drop_ended_reference()
            old = self.inherited
            resume = (old is not None and (old.width, old.height) == (msg.width, msg.height)
                      and old.stamp_ns <= self.first_stamp_ns)  # a reference stamped later is another stream's
            if not resume and time.monotonic() < self.resume_until:
                return
            take_next = self.take_next or self.after_previous_reset()
            if not resume and not take_next and self.frame_number(msg) < self.params.reference_frame:
                if self.frames_seen == 1:  # a video shorter than that is never tracked: say why
                    self.log.info("frames before frame %d (reference_frame) are not tracked",
                                  self.params.reference_frame)
                return
            try:
                state = self.perception.resume(image, old.ref_px) if resume else self.perception.reset(image)
            except ValueError as exc:  # a dark or empty frame (a camera starting): the next one is tried
                self.counters["reference_retries"] += 1
                self.warn(f"no reference in this frame ({exc}): taking the next (reference_retries)",
                          kind="no reference")
                return
            if resume:
                self.counters["resumed"] += 1
                self.log.info("tracking against %s reference (%d markers)", self.inherited_from, len(old.ref_px))
            else:
                self.counters["references"] += 1
            self.clear_warning()
            self.needs_reference = False
            self.take_next = False
            self.inherited = None
            self.own_grasp = True
            # a resumed reference is published as it was taken (its frame's stamp): the grasp under way goes on
            self.reference_pub.publish(replace(old) if resume else marker_array(state, msg))
        try:
            detections = self.perception.detect(image)
        except ValueError as exc:  # a camera reopened at another size: its markers are not the reference's
            self.counters["other_size"] += 1
            self.warn(f"frame dropped: {exc} (publish on /tracker/reset) (other_size)", kind="other size")
            return
        state = self.perception.tracker.step(detections)
        self.markers_pub.publish(marker_array(state, msg))
        self.counters["valid_markers"] = int(state.valid.sum())
