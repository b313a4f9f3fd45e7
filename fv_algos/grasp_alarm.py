"""How early the running P(slip) of grasps in progress tells slips from held grasps.

After every frame t of a grasp (frame 0: the tracker's reference, t / fps seconds later), the
pipeline's slip detector publishes P(slip) of the grasp so far, one camera per slip detector
(:func:`fv_algos.trial_net.running_probability` gives the same series offline). From such series of
labelled grasps, one per camera, :func:`online_summary` measures

- the share of held and of slipping grasps' cameras at P(slip) >= 0.5 at given times, among the
  cameras still recording then;
- alarm rules (:class:`AlarmRule`): the share of held and of slip cameras that would have raised
  the alarm at all, and the median time of the slips' first alarm;
- one camera's accuracy at the end of its grasp.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

RunningSeries = Sequence[Sequence[np.ndarray]]  # per grasp, per camera: (F,) running P(slip)


@dataclass(frozen=True)
class AlarmRule:
    """Alarm when P(slip) >= ``threshold`` for ``in_row`` frames in a row, counting only frames
    from ``from_frame`` on (frame 0: the grasp's reference)."""

    threshold: float
    from_frame: int = 0
    in_row: int = 1

    def __post_init__(self) -> None:
        if not (0.0 <= self.threshold <= 1.0 and self.from_frame >= 0 and self.in_row >= 1):
            raise ValueError(f"AlarmRule needs 0 <= threshold <= 1, from_frame >= 0 and in_row >= 1, got {self}")

    @classmethod
    def parse(cls, text: str) -> AlarmRule:
        """The rule of ``"P[:FROM[:ROW]]"`` (threshold, first frame counted, frames in a row), e.g.
        ``"0.95:50:10"``; ValueError naming ``text`` when it is not one."""
        parts = text.split(":")
        try:
            if not 1 <= len(parts) <= 3:
                raise ValueError("expected P, P:FROM or P:FROM:ROW")
            return cls(float(parts[0]), *(int(p) for p in parts[1:]))
        except ValueError as error:
            raise ValueError(f"alarm rule {text!r}: {error}") from None

    def first_alarm(self, running: np.ndarray) -> int | None:
        """The frame at which the alarm is raised over ``running`` (F,) P(slip), the last of the
        first ``in_row`` frames in a row at or above the threshold (none before ``from_frame``
        count); None when it never is."""
        above = np.asarray(running) >= self.threshold
        above[:self.from_frame] = False
        if above.size < self.in_row:
            return None
        runs = np.convolve(above, np.ones(self.in_row, np.int64), mode="valid") == self.in_row
        hits = np.flatnonzero(runs)
        return int(hits[0]) + self.in_row - 1 if hits.size else None

    def __str__(self) -> str:
        return f"P >= {self.threshold:g} from frame {self.from_frame}, {self.in_row} in a row"


DEFAULT_TIMES_S = (0.4, 1.0, 2.0, 4.0, 8.0, 12.0)
DEFAULT_RULES = (AlarmRule(0.5), AlarmRule(0.5, 0, 10), AlarmRule(0.95, 0, 10), AlarmRule(0.5, 50, 10),
                 AlarmRule(0.95, 50, 10), AlarmRule(0.99, 50, 10), AlarmRule(0.99, 100, 10))


def _cameras(running: RunningSeries, labels: np.ndarray) -> dict[int, list[np.ndarray]]:
    """The cameras' running P(slip) by label (0: held, 1: slip); ValueError when ``running`` and
    ``labels`` count different grasps or a camera has no frame."""
    if len(running) != len(labels):
        raise ValueError(f"{len(running)} grasps' running P(slip) but {len(labels)} labels")
    by_label: dict[int, list[np.ndarray]] = {0: [], 1: []}
    for label, cameras in zip(labels, running):
        for series in cameras:
            series = np.asarray(series, np.float64)
            if series.size == 0:
                raise ValueError("a camera's running P(slip) has no frame")
            by_label[int(label)].append(series)
    return by_label


def _share(flags: Sequence[bool]) -> float | None:
    """Share of true ``flags`` (None when there are none)."""
    return float(np.mean(flags)) if len(flags) else None


def above_curves(running: RunningSeries, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T,) shares of held (label 0) and of slip cameras at P(slip) >= 0.5 after every frame t, among
    the cameras still recording at t (T: the longest camera's frames; NaN where none of a label is)."""
    by_label = _cameras(running, labels)
    frames = max(s.size for cameras in by_label.values() for s in cameras)
    curves = []
    for label in (0, 1):
        above, recording = np.zeros(frames), np.zeros(frames)
        for series in by_label[label]:
            above[:series.size] += series >= 0.5
            recording[:series.size] += 1
        curves.append(np.divide(above, recording, out=np.full(frames, np.nan), where=recording > 0))
    return curves[0], curves[1]


def online_summary(running: RunningSeries, labels: np.ndarray, fps: float,
                   times_s: Sequence[float] = DEFAULT_TIMES_S,
                   rules: Sequence[AlarmRule] = DEFAULT_RULES) -> dict[str, object]:
    """Running P(slip) of grasps with ``labels`` (M,) 0/1, measured at ``times_s`` (s after the
    reference, frame round(s * fps)) and under ``rules``: {"cameras": held and slip cameras;
    "camera_end_accuracy"; "at": per time, the share of held / slip cameras at P >= 0.5 and how many
    of each still record; "alarms": per rule, the share of held / slip cameras alarmed and the
    slips' median first alarm (s)}. Shares are None where no camera counts."""
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    by_label = _cameras(running, labels)
    held, slips = by_label[0], by_label[1]
    at = []
    for seconds in times_s:
        frame = int(round(seconds * fps))
        row: dict[str, object] = {"seconds": seconds, "frame": frame}
        for name, cameras in (("held", held), ("slip", slips)):
            recording = [s[frame] >= 0.5 for s in cameras if s.size > frame]
            row[f"{name}_above"], row[f"{name}_recording"] = _share(recording), len(recording)
        at.append(row)
    alarms = []
    for rule in rules:
        first = [rule.first_alarm(s) for s in slips]
        rung = [f for f in first if f is not None]
        alarms.append({"rule": str(rule), "threshold": rule.threshold, "from_frame": rule.from_frame,
                       "in_row": rule.in_row,
                       "held_alarmed": _share([rule.first_alarm(s) is not None for s in held]),
                       "slip_alarmed": _share([f is not None for f in first]),
                       "slip_median_first_s": float(np.median(rung)) / fps if rung else None})
    end = [(s[-1] >= 0.5) == label for label, cameras in by_label.items() for s in cameras]
    return {"fps": fps, "cameras": {"held": len(held), "slip": len(slips)},
            "camera_end_accuracy": _share(end), "at": at, "alarms": alarms}
