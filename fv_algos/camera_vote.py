"""One grasp's P(slip) from the P(slip) of each of its cameras, as the trial network
(:mod:`fv_algos.trial_net`) judges all the cameras of a trial together: :func:`camera_vote`, and
:class:`CameraVote`, which keeps the cameras' latest answers while the grasp goes on and says which
count. No torch: the slip fusion node imports it."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.special import expit, logit

EXPECTED = ("starting", "switching grasp")  # reasons to leave a camera out of a vote that are no fault
LOGIT_LIMIT = 36.0  # |logit| a float64 P(slip) holds (1 - P rounds to 0 beyond it); beyond counts as this


def camera_vote(probabilities: Sequence[float]) -> float:
    """P(slip) of a grasp from its cameras' P(slip), each judged alone (one
    `fv_algos.grasp_judge.GraspJudge` per camera): what the trial network says of the cameras
    together. Its logit is the mean of the cameras' logits, since the network averages the cameras'
    pooled features and its head is linear. The logits are taken back from float64 probabilities,
    exactly while |logit| < `LOGIT_LIMIT`."""
    if len(probabilities) == 0:
        raise ValueError("camera_vote needs at least one camera's P(slip)")
    with np.errstate(divide="ignore"):  # P 0 or 1: logit -inf or +inf, clipped
        z = np.clip(logit(np.asarray(probabilities, np.float64)), -LOGIT_LIMIT, LOGIT_LIMIT)
    return float(expit(z.mean()))


@dataclass(frozen=True)
class CameraAnswer:
    """One camera's latest answer: stamp_ns, capture stamp of its frame; grasp_start_ns, of its grasp's
    first frame; last_judged_ns, of the last frame the model judged; probability, P(slip) of the grasp so
    far; valid, False for an answer that does not count (e.g. an invalid window)."""

    stamp_ns: int
    grasp_start_ns: int
    last_judged_ns: int
    probability: float
    valid: bool = True


@dataclass(frozen=True)
class Vote:
    """The vote after an answer: probability (None when no camera counts); newest_grasp_ns, the latest
    grasp start of the fresh answers, on the caller's wall clock (:meth:`CameraVote.grasp_start_on_clock_ns`);
    first_ns, last_ns, the first grasp start and last judged stamp of the cameras that count, as they
    stamped them (with none: the newest grasp start and answer); voters; and why each other
    camera is left out, by name (an invalid answer is left out without a reason). Faults: "no answer
    yet" (none arrived ``stale_after_s`` after the first camera's first), "stale" (none arrived for
    ``stale_after_s``) or "earlier grasp" (still on one ``same_grasp_s`` after the newest grasp
    started). Expected, for a frame or so: "starting" (no answer yet, within ``stale_after_s`` of the
    first camera's first) and "switching grasp" (on an earlier grasp with an answer from before the
    newest grasp started or within ``same_grasp_s`` of it: after a reset, a camera whose next frame has
    not come yet)."""

    probability: float | None
    newest_grasp_ns: int
    first_ns: int
    last_ns: int
    voters: tuple[str, ...]
    left_out: dict[str, str]

    def faults(self) -> dict[str, str]:
        """The cameras left out for a fault (``left_out`` but "starting" and "switching grasp")."""
        return {name: why for name, why in self.left_out.items() if why not in EXPECTED}


class StampAhead(ValueError):
    """An answer refused by :meth:`CameraVote.update`: stamped ``ahead_s`` (s) ahead of every camera's
    clock and the caller's, more than ``stale_after_s``."""

    def __init__(self, camera: str, ahead_s: float) -> None:
        super().__init__(f"{camera}: answer stamped {ahead_s:.1f} s ahead of every clock")
        self.camera, self.ahead_s = camera, ahead_s


class CameraVote:
    """The vote of named cameras' latest answers (:func:`camera_vote`). Left out: a camera with no answer
    arrived within ``stale_after_s`` (a camera that stopped), and one still on an earlier grasp, whose
    grasp started more than ``same_grasp_s`` before the newest (after a reset every camera starts a new
    grasp with its next frame: a vote never mixes grasps). :class:`Vote` tells the faults from what
    every start and every reset brings for a frame or so.

    Staleness is judged by arrival, on the caller's monotonic clock: by capture stamps, a camera whose
    clock ran 2 s behind was left out for good while its answers came, and one answer stamped an hour
    ahead made every other camera stale. Such an answer is refused (:class:`StampAhead`)."""

    def __init__(self, cameras: Sequence[str], stale_after_s: float = 1.0, same_grasp_s: float = 1.0) -> None:
        if len(cameras) < 2 or len(set(cameras)) != len(cameras):
            raise ValueError(f"cameras {list(cameras)} must be two or more different names")
        if stale_after_s <= 0 or same_grasp_s <= 0:
            raise ValueError(f"stale_after_s {stale_after_s} and same_grasp_s {same_grasp_s} must be > 0")
        self.cameras = tuple(cameras)
        self.stale_after_ns, self.same_grasp_ns = stale_after_s * 1e9, same_grasp_s * 1e9
        self.latest: dict[str, CameraAnswer] = {}
        self.arrived_s: dict[str, float] = {}  # when each camera's latest answer arrived (caller's clock, s)
        self.arrival_ns: dict[str, int] = {}  # the caller's wall clock then (ns)
        self.seen: dict[str, tuple[int, float]] = {}  # each camera's last stamp (refused or not) and its arrival
        self.first_s: float | None = None  # arrival of the first answer of any camera

    def grasp_start_on_clock_ns(self, camera: str) -> int:
        """When ``camera``'s current grasp started, on the caller's wall clock (ns): its grasp start
        moved by the offset of its latest answer's arrival to its stamp (that camera's clock offset
        and latency), so that cameras whose clocks differ compare grasps as the caller sees them."""
        answer = self.latest[camera]
        return answer.grasp_start_ns + self.arrival_ns[camera] - answer.stamp_ns

    def ahead_s(self, stamp_ns: int, arrived_s: float, clock_ns: int) -> float:
        """How far (s) ``stamp_ns``, arrived at ``arrived_s`` (monotonic s) when the caller's wall
        clock read ``clock_ns``, is ahead of every clock: of that wall clock, and of the last stamp each
        camera sent advanced by the time since it arrived. A camera whose clock is behind is not ahead of
        its own last answer; cameras on a host whose clock is ahead of the caller's are not ahead of
        their own; answers whose latency fell (a detector catching up) are not ahead of the wall clock."""
        host_s = (stamp_ns - clock_ns) / 1e9
        if not self.seen:
            return host_s
        return min(host_s, (stamp_ns - max(s + (arrived_s - a) * 1e9 for s, a in self.seen.values())) / 1e9)

    def update(self, camera: str, answer: CameraAnswer, arrived_s: float, clock_ns: int) -> Vote:
        """Take ``camera``'s newest answer, arrived at ``arrived_s`` (s, the caller's monotonic clock)
        when its wall clock read ``clock_ns``; the vote of all the cameras' latest (:meth:`admit`, then
        :meth:`take`)."""
        self.admit(camera, answer.stamp_ns, arrived_s, clock_ns)
        return self.take(camera, answer, arrived_s, clock_ns)

    def admit(self, camera: str, stamp_ns: int, arrived_s: float, clock_ns: int) -> None:
        """Check an answer of ``camera`` stamped ``stamp_ns`` as it arrives (at ``arrived_s``, the wall
        clock then ``clock_ns``): StampAhead for one stamped more than ``stale_after_s`` ahead of every
        clock (:meth:`ahead_s`), to be left out; a camera whose clock jumped ahead counts again from its
        next answer."""
        ahead_s = self.ahead_s(stamp_ns, arrived_s, clock_ns)
        self.seen[camera] = (stamp_ns, arrived_s)
        if ahead_s * 1e9 > self.stale_after_ns:
            raise StampAhead(camera, ahead_s)

    def take(self, camera: str, answer: CameraAnswer, arrived_s: float, clock_ns: int) -> Vote:
        """The vote of all the cameras' latest with ``answer``, admitted (:meth:`admit`) when it arrived
        at ``arrived_s`` (wall clock ``clock_ns``), as ``camera``'s newest. Answers may be taken later than
        they arrived, in another order (:class:`fv_algos.stamp_order.StampOrder`): staleness is judged
        at ``arrived_s``."""
        self.latest[camera], self.arrived_s[camera] = answer, arrived_s
        self.arrival_ns[camera] = clock_ns
        self.first_s = arrived_s if self.first_s is None else min(self.first_s, arrived_s)
        fresh = {c: a for c, a in self.latest.items() if (arrived_s - self.arrived_s[c]) * 1e9 <= self.stale_after_ns}
        now = max(a.stamp_ns for a in fresh.values())
        grasp = max(self.grasp_start_on_clock_ns(c) for c in fresh)
        left_out, voters = {}, {}
        for name in self.cameras:
            if name not in self.latest:
                late = (arrived_s - self.first_s) * 1e9 > self.stale_after_ns
                left_out[name] = "no answer yet" if late else "starting"
            elif name not in fresh:
                left_out[name] = "stale"
            elif grasp - self.grasp_start_on_clock_ns(name) > self.same_grasp_ns:
                late = self.arrival_ns[name] - grasp > self.same_grasp_ns
                left_out[name] = "earlier grasp" if late else "switching grasp"
            elif fresh[name].valid:
                voters[name] = fresh[name]
        if not voters:
            return Vote(None, grasp, grasp, now, (), left_out)
        return Vote(camera_vote([a.probability for a in voters.values()]), grasp,
                    min(a.grasp_start_ns for a in voters.values()), max(a.last_judged_ns for a in voters.values()),
                    tuple(voters), left_out)
