"""The `slip_fusion` node: one slip decision from several cameras' slip detectors, e.g. the two
fingers of a gripper (`launch/gelsight_mini_pair.yaml`).

Each input is a `SlipState` topic (`/left/slip`, `/right/slip`). On every state that comes in, the
node publishes on `output` the vote of the inputs' latest states: P(slip) whose logit is the mean
of theirs (`fv_algos.camera_vote`, what a trial model says of all the cameras of a
grasp together, as `fv eval --trials` judges both cameras), slip when it reaches the threshold.

Left out of a vote, and named in the node's warning:
- an input with no state within `stale_after_s` of the newest state (by capture stamp): a
  camera that stopped;
- an input still on an earlier grasp: its grasp (window_stamps_ns[0], the tracker's reference)
  started more than `same_grasp_s` before the newest grasp of the inputs. After `/tracker/reset`
  every camera starts a new grasp with its next frame, so the vote is never a mix of grasps;
  trackers that took their references far apart (cameras started at different times) are brought
  together by one message on `/tracker/reset`.
An invalid state (a window model's invalid window) is left out as well; with no input left, the
state published is invalid (probability 0)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fv_algos.camera_vote import camera_vote
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
        if self.stale_after_s <= 0 or self.same_grasp_s <= 0:
            raise ValueError(f"stale_after_s {self.stale_after_s} and same_grasp_s {self.same_grasp_s} must be > 0")


def _grasp_start(msg: SlipState) -> int:
    """Capture stamp (ns) of the first frame the state judged: a trial model's grasp start."""
    return int(msg.window_stamps_ns[0]) if len(msg.window_stamps_ns) else msg.stamp_ns


class SlipFusion(Node):
    """The cameras' vote on `output` after every input state; counters `voted` (states published),
    `alone` (of them, votes of one input), `stale` and `earlier_grasp` (inputs left out, by why)."""

    Params = SlipFusionParams

    def setup(self) -> None:
        p = self.params
        self.latest: dict[str, SlipState] = {}
        self.pub = self.publisher(p.output, SlipState)
        self.counters.update(voted=0, alone=0, stale=0, earlier_grasp=0)
        for topic in p.inputs:
            self.subscribe(topic, SlipState, lambda msg, topic=topic: self.on_state(topic, msg), depth=None)

    def on_state(self, topic: str, msg: SlipState) -> None:
        self.latest[topic] = msg
        self.pub.publish(self.vote(msg))

    def vote(self, newest: SlipState) -> SlipState:
        """The state published after `newest` came in: the vote of the inputs that count."""
        p = self.params
        now = max(m.stamp_ns for m in self.latest.values())
        fresh = {t: m for t, m in self.latest.items() if now - m.stamp_ns <= p.stale_after_s * 1e9}
        grasp = max(_grasp_start(m) for m in fresh.values())
        voters = {t: m for t, m in fresh.items() if grasp - _grasp_start(m) <= p.same_grasp_s * 1e9 and m.valid}
        left_out = self._left_out(fresh, grasp)
        if left_out:
            self.warn("; ".join(left_out))
        else:
            self.clear_warning()
        self.counters["voted"] += 1
        self.counters["alone"] += len(voters) == 1
        if not voters:
            return SlipState(stamp_ns=newest.stamp_ns, threshold=newest.threshold, model=newest.model, valid=False,
                             window_stamps_ns=np.array([grasp, now], np.int64))
        probability = camera_vote([m.probability for m in voters.values()])
        first = min(_grasp_start(m) for m in voters.values())
        last = max(int(m.window_stamps_ns[-1]) if len(m.window_stamps_ns) else m.stamp_ns for m in voters.values())
        return SlipState(stamp_ns=newest.stamp_ns, probability=probability, slip=probability >= newest.threshold,
                         threshold=newest.threshold, model=newest.model,
                         window_stamps_ns=np.array([first, last], np.int64))

    def _left_out(self, fresh: dict[str, SlipState], grasp: int) -> list[str]:
        """Why each input is left out of the vote (counted), in words."""
        p = self.params
        why = []
        for topic in p.inputs:
            if topic not in self.latest:
                why.append(f"{topic}: no state yet")
            elif topic not in fresh:
                self.counters["stale"] += 1
                why.append(f"{topic}: no state for {p.stale_after_s} s")
            elif grasp - _grasp_start(fresh[topic]) > p.same_grasp_s * 1e9:
                self.counters["earlier_grasp"] += 1
                ahead = (grasp - _grasp_start(fresh[topic])) / 1e9
                why.append(f"{topic}: on an earlier grasp ({ahead:.1f} s before the newest; "
                           f"one message on /tracker/reset starts every camera's grasp together)")
        return why
