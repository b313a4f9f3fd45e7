"""The `slip_fusion` node: one slip decision from several cameras' slip detectors, e.g. the two
fingers of a gripper (`launch/gelsight_mini_pair.yaml`).

Each input is a `SlipState` topic (`/left/slip`, `/right/slip`). On every state that comes in, the
node publishes on `output` the vote of the inputs' latest states (`fv_algos.camera_vote.CameraVote`):
P(slip) whose logit is the mean of theirs, what a trial model says of all the cameras of a grasp
together, as `fv eval --trials` judges both cameras; slip when it reaches the threshold.

Left out of a vote, and named in the node's warning:
- an input with no state within `stale_after_s` of the newest state (by capture stamp): a
  camera that stopped; or none yet `stale_after_s` after the first input's first state;
- an input still on an earlier grasp: its grasp (window_stamps_ns[0], the tracker's reference)
  started more than `same_grasp_s` before the newest grasp of the inputs, and it has given a state
  `same_grasp_s` after that newest grasp started. Trackers that took their references far apart
  (cameras started at different times) are brought together by one message on `/tracker/reset`.
Left out without a warning: an input with no state yet at the start, and, after `/tracker/reset`,
one whose next frame (which starts its new grasp) has not come yet (counter `switching`): so the
vote is never a mix of grasps, and every grasp does not raise a warning. An invalid state (a window
model's invalid window) is left out as well; with no input left, the state published is invalid
(probability 0)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fv_algos.camera_vote import CameraAnswer, CameraVote, Vote
from msgs import SlipState
from nodes.node import Node


@dataclass
class SlipFusionParams:
    inputs: list[str] = field(default_factory=lambda: ["/left/slip", "/right/slip"])  # SlipState topics
    output: str = "/slip"
    stale_after_s: float = 1.0  # an input with no state this long before the newest is left out
    same_grasp_s: float = 1.0  # grasps that started further apart than this are different grasps

    def __post_init__(self) -> None:
        if len(self.inputs) < 2 or len(set(self.inputs)) != len(self.inputs):
            raise ValueError(f"inputs {self.inputs} must name two or more different topics")
        if self.output in self.inputs:
            raise ValueError(f"output {self.output!r} is also an input")
        CameraVote(self.inputs, self.stale_after_s, self.same_grasp_s)  # ValueError names a bad duration


def _answer(msg: SlipState) -> CameraAnswer:
    """A slip detector's state as the vote takes it: a trial model's window_stamps_ns hold its grasp's
    first stamp and its last judged (a window model's, its window's first and last)."""
    stamps = msg.window_stamps_ns
    first, last = (int(stamps[0]), int(stamps[-1])) if len(stamps) else (msg.stamp_ns, msg.stamp_ns)
    return CameraAnswer(msg.stamp_ns, first, last, msg.probability, msg.valid)


class SlipFusion(Node):
    """The cameras' vote on `output` after every input state; counters `voted` (states published),
    `alone` (of them, votes of one input), `stale`, `earlier_grasp` and `switching` (inputs left out,
    by why)."""

    Params = SlipFusionParams

    def setup(self) -> None:
        p = self.params
        self.vote = CameraVote(p.inputs, p.stale_after_s, p.same_grasp_s)
        self.pub = self.publisher(p.output, SlipState)
        self.counters.update(voted=0, alone=0, stale=0, earlier_grasp=0, switching=0)
        for topic in p.inputs:
            self.subscribe(topic, SlipState, lambda msg, topic=topic: self.on_state(topic, msg), depth=None)

    def on_state(self, topic: str, msg: SlipState) -> None:
        vote = self.vote.update(topic, _answer(msg))
        self._report(vote)
        stamps = np.array([vote.first_ns, vote.last_ns], np.int64)
        if vote.probability is None:
            state = SlipState(stamp_ns=msg.stamp_ns, threshold=msg.threshold, model=msg.model, valid=False,
                              window_stamps_ns=stamps)
        else:
            state = SlipState(stamp_ns=msg.stamp_ns, probability=vote.probability,
                              slip=vote.probability >= msg.threshold, threshold=msg.threshold, model=msg.model,
                              window_stamps_ns=stamps)
        self.pub.publish(state)

    def _report(self, vote: Vote) -> None:
        """Count the vote and the inputs left out of it, and name them in the node's warning."""
        self.counters["voted"] += 1
        self.counters["alone"] += len(vote.voters) == 1
        self.counters["switching"] += sum(reason == "switching grasp" for reason in vote.left_out.values())
        why = []
        for topic, reason in vote.faults().items():
            if reason == "no answer yet":
                why.append(f"{topic}: no state yet")
            elif reason == "stale":
                self.counters["stale"] += 1
                why.append(f"{topic}: no state for {self.params.stale_after_s} s")
            else:
                self.counters["earlier_grasp"] += 1
                ahead = (vote.newest_grasp_ns - self.vote.latest[topic].grasp_start_ns) / 1e9
                why.append(f"{topic}: on an earlier grasp ({ahead:.1f} s before the newest; "
                           f"one message on /tracker/reset starts every camera's grasp together)")
        if why:
            self.warn("; ".join(why))
        else:
            self.clear_warning()
