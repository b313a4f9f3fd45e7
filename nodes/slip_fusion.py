"""The `slip_fusion` node: one slip decision from several cameras' slip detectors, e.g. the two
fingers of a gripper (`launch/gelsight_mini_pair.yaml`).

Each input is a `SlipState` topic (`/left/slip`, `/right/slip`). For every input state the node
publishes on `output` the vote of the inputs' latest states (`fv_algos.camera_vote.CameraVote`):
P(slip) whose logit is the mean of theirs, what a trial model says of all the cameras of a grasp
together, as `fv eval --trials` judges both cameras; slip when it reaches the node's own `threshold`
(the inputs' thresholds are not read: one input with threshold 0 made every vote slip).

`order` says which states are the latest. `arrival` (default): each state is voted as it arrives,
with the others' latest arrived, at once; which of two fingers' states of one instant comes first
decides the vote, and that varies from run to run. `stamp`: states are voted in the order of their
capture stamps, each with every other input's latest state stamped at or before it (states of one
stamp are voted together), so a replayed recording gives the same votes on every replay; a state
waits until every other input has sent one stamped at or after it, or `wait_s` (to within the
timer's `wait_s` / 5; `fv_algos.stamp_order.StampOrder`: counters `waited`, `late`, `restarts`).

Left out of a vote, and named in the node's warning:
- an input with no state arrived for `stale_after_s` (by arrival on the node's monotonic clock, not
  by capture stamp: a camera whose clock is behind still counts while its states come): a camera
  that stopped; or none yet `stale_after_s` after the first input's first state;
- a state stamped more than `stale_after_s` ahead of every input's clock and this host's
  (`CameraVote.ahead_s`): refused, counted in `ahead`, and no vote published for it;
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

import math
import time
from dataclasses import dataclass, field
from itertools import groupby
from typing import Callable

import numpy as np

from fv_algos.camera_vote import CameraAnswer, CameraVote, StampAhead, Vote
from fv_algos.stamp_order import StampOrder
from msgs import SlipState
from nodes.bus import resolve_topic
from nodes.node import Node


@dataclass
class SlipFusionParams:
    inputs: list[str] = field(default_factory=lambda: ["/left/slip", "/right/slip"])  # SlipState topics
    output: str = "/slip"
    threshold: float = 0.5  # the vote's P(slip) at or above which `output` says slip
    stale_after_s: float = 1.0  # an input with no state arrived for this long is left out
    same_grasp_s: float = 1.0  # grasps that started further apart than this are different grasps
    order: str = "arrival"  # "arrival": vote each state as it arrives; "stamp": in capture stamp order
    wait_s: float = 0.5  # order "stamp": how long a state waits for the other inputs' states

    def __post_init__(self) -> None:
        check_topics(self.inputs, self.output, resolve_topic)  # as a node without a namespace reads them
        if not 0.0 < self.threshold < 1.0:
            raise ValueError(f"threshold {self.threshold} must be in (0, 1)")
        if self.order not in ORDERS:
            raise ValueError(f"order {self.order!r} must be one of {', '.join(ORDERS)}")
        if not MIN_WAIT_S <= self.wait_s < math.inf:  # the timer, every wait_s / 5, would starve the inputs
            raise ValueError(f"wait_s {self.wait_s} must be at least {MIN_WAIT_S} s and finite")
        CameraVote(self.inputs, self.stale_after_s, self.same_grasp_s)  # ValueError names a bad duration


ORDERS = ("arrival", "stamp")
MIN_WAIT_S = 0.05  # s: the stamp order's timer ticks every wait_s / 5


@dataclass(frozen=True)
class _Arrival:
    """An input state as it arrived: at `arrived_s` on the node's monotonic clock, its wall clock then `clock_ns`."""

    msg: SlipState
    arrived_s: float
    clock_ns: int


def check_topics(inputs: list[str], output: str, resolve: Callable[[str], str]) -> list[str]:
    """The input topics as `resolve` reads them; ValueError unless they are two or more different
    topics, `output` not among them (`left/slip` and `/left/slip` are one topic at the root)."""
    names = [resolve(t) for t in inputs]
    if len(names) < 2 or len(set(names)) != len(names):
        raise ValueError(f"inputs {inputs} must name two or more different topics (they read {names})")
    if resolve(output) in names:
        raise ValueError(f"output {output!r} is also an input")
    return names


def _answer(msg: SlipState) -> CameraAnswer:
    """A slip detector's state as the vote takes it: a trial model's window_stamps_ns hold its grasp's
    first stamp and its last judged (a window model's, its window's first and last)."""
    stamps = msg.window_stamps_ns
    first, last = (int(stamps[0]), int(stamps[-1])) if len(stamps) else (msg.stamp_ns, msg.stamp_ns)
    return CameraAnswer(msg.stamp_ns, first, last, msg.probability, msg.valid)


class SlipFusion(Node):
    """The cameras' vote on `output` for every input state; counters `voted` (states published),
    `alone` (of them, votes of one input), `stale`, `earlier_grasp` and `switching` (inputs left out,
    by why), `ahead` (states refused), and with order `stamp` `waited`, `late`, `restarts`
    (:class:`fv_algos.stamp_order.StampOrder`). `clock`: the monotonic clock (s) arrivals are read on,
    `wall_clock` the wall clock (ns since the epoch) stamps are compared with."""

    Params = SlipFusionParams
    LIVE_PARAMS = frozenset({"threshold"})  # read by each vote (`fv param set`)
    order: StampOrder[_Arrival] | None = None  # order `stamp`: the states held until due

    def setup(self) -> None:
        p = self.params
        inputs = check_topics(p.inputs, p.output, self.resolve)  # again with the namespace and remaps
        self.clock: Callable[[], float] = time.monotonic
        self.wall_clock: Callable[[], int] = time.time_ns
        self.vote = CameraVote(inputs, p.stale_after_s, p.same_grasp_s)
        self.order = StampOrder(inputs, p.wait_s, p.stale_after_s) if p.order == "stamp" else None
        self.pub = self.publisher(p.output, SlipState)
        self.counters.update(voted=0, alone=0, stale=0, earlier_grasp=0, switching=0, ahead=0)
        if self.order is not None:
            self.counters.update(self.order.counters)
            self.timer(p.wait_s / 5, self.on_timer)
        for topic, name in zip(p.inputs, inputs):
            self.subscribe(topic, SlipState, lambda msg, name=name: self.on_state(name, msg), depth=None)

    def on_state(self, topic: str, msg: SlipState) -> None:
        """Take `msg`, the newest state of the input `topic` (its resolved name): vote with it and publish,
        at once (order `arrival`) or with the states due in stamp order (order `stamp`)."""
        arrival = _Arrival(msg, self.clock(), self.wall_clock())
        try:
            self.vote.admit(topic, msg.stamp_ns, arrival.arrived_s, arrival.clock_ns)
        except StampAhead as exc:
            self.counters["ahead"] += 1
            self.warn(f"{topic}: state refused, stamped {exc.ahead_s:.1f} s ahead of every input's clock and "
                      f"this host's (stale_after_s {self.params.stale_after_s} s; counter ahead)",
                      kind=f"{topic}: ahead")
            return
        if self.order is None:
            self._publish(self._take(topic, arrival), arrival)
        else:
            self._publish_due(self.order.push(topic, msg.stamp_ns, arrival, arrival.arrived_s))

    def teardown(self) -> None:
        """Order `stamp`: publish the votes of the states still held (a replay's last ones) before the node ends."""
        if self.order is not None:
            self._publish_due(self.order.flush())

    def on_timer(self) -> None:
        """Order `stamp`: publish the votes of the states that have waited `wait_s`."""
        self._publish_due(self.order.due(self.clock()))

    def _publish_due(self, due: list[tuple[str, _Arrival]]) -> None:
        """Publish the votes of the states `due` in stamp order: each state of one stamp with the vote of them
        all (every input's latest stamped at or before it)."""
        for _, same in groupby(due, key=lambda item: item[1].msg.stamp_ns):
            same = list(same)
            vote = [self._take(topic, arrival) for topic, arrival in same][-1]
            for _, arrival in same:
                self._publish(vote, arrival)
        self.counters.update(self.order.counters)

    def _take(self, topic: str, arrival: _Arrival) -> Vote:
        """The vote with `arrival`'s state as the newest of the input `topic`."""
        return self.vote.take(topic, _answer(arrival.msg), arrival.arrived_s, arrival.clock_ns)

    def _publish(self, vote: Vote, arrival: _Arrival) -> None:
        """Publish `vote`, taken for `arrival`'s state, stamped as it."""
        msg = arrival.msg
        self._report(vote, arrival.arrived_s)
        stamps = np.array([vote.first_ns, vote.last_ns], np.int64)
        threshold = self.params.threshold
        if vote.probability is None:
            state = SlipState(stamp_ns=msg.stamp_ns, threshold=threshold, model=msg.model, valid=False,
                              window_stamps_ns=stamps)
        else:
            state = SlipState(stamp_ns=msg.stamp_ns, probability=vote.probability,
                              slip=vote.probability >= threshold, threshold=threshold, model=msg.model,
                              window_stamps_ns=stamps)
        self.pub.publish(state)

    def _report(self, vote: Vote, now_s: float) -> None:
        """Count the vote (taken at `now_s`, the node's clock) and the inputs left out of it, and name
        them in the node's warning."""
        self.counters["voted"] += 1
        self.counters["alone"] += len(vote.voters) == 1
        self.counters["switching"] += sum(reason == "switching grasp" for reason in vote.left_out.values())
        why = []
        faults = vote.faults()
        for topic, reason in faults.items():
            if reason == "no answer yet":
                why.append(f"{topic}: no state yet")
            elif reason == "stale":
                self.counters["stale"] += 1
                why.append(f"{topic}: no state for {now_s - self.vote.arrived_s[topic]:.1f} s")
            else:
                self.counters["earlier_grasp"] += 1
                ahead = (vote.newest_grasp_ns - self.vote.grasp_start_on_clock_ns(topic)) / 1e9
                why.append(f"{topic}: on an earlier grasp ({ahead:.1f} s before the newest; "
                           f"one message on /tracker/reset starts every camera's grasp together)")
        if why:
            self.warn("; ".join(why), kind="; ".join(f"{topic}: {reason}" for topic, reason in faults.items()))
        else:
            self.clear_warning()
