"""A window slip model judged frame by frame on the simulated camera's endless random grasps (the
stream the main job runs on) against the simulator's truth.

The camera (:class:`fv_algos.sim.sensor.SimSensor` without a scene) plays random scenarios, each as a
whole grasp from the skin at rest; perception takes its first frame as the reference, as the tracker
node does; after each frame the model reads the window of the last ``window`` fields, as the slip
detector node does. Every frame from the first full window on is scored against its truth (incipient
and gross slip are slip), in all and per scripted action (press, hold, shear, slide, twist, release),
so that the frames a model gets wrong can be told apart: a window still holding the last motion, a
release read as slip, a shear near the friction limit. The frames whose window holds a change of the
truth are also scored apart (``transition``): there a window model lags by up to its window.
"""
from __future__ import annotations

from collections import defaultdict, deque
from itertools import islice

import numpy as np

from fv_algos.perception import Perception, PerceptionParams
from fv_algos.sim.scene import MAX_SCENE_FRAMES
from fv_algos.sim.sensor import SimSensor
from fv_algos.slip.classifier import SlipClassifier


def judge_stream(classifier: SlipClassifier, seconds: float, fps: float, seed: int = 0, threshold: float = 0.5,
                 preset: str = "default") -> dict[str, object]:
    """Score ``classifier`` on ``seconds`` s of the random grasps at ``fps`` Hz (simulator seed ``seed``,
    tracker ``preset``), slip when P(slip) >= ``threshold``.

    Returns frames_judged, accuracy, slip_share (of the frames judged, by truth), held_called_slip and
    slip_called_slip (shares of the held / slipping frames called slip; None without such frames),
    ``phases``: action -> {frames, slip_share, accuracy}, and ``transition``: {share (of the frames
    judged whose window's truth changes within it), accuracy there and on the other frames
    (``steady_accuracy``), ``slip_before_called_slip`` (of the windows held at their last field but
    slipping earlier in them, the share called slip: the window's lag)}; an accuracy or share is None
    without such frames. ValueError when the stream is shorter than one window, or longer than
    MAX_SCENE_FRAMES (about 11 ms a frame here: `--stream 3 --fps 1e5` ran for about an hour without a word).
    """
    window = classifier.config.window
    frames = int(round(seconds * fps))
    if frames < window:
        raise ValueError(f"{seconds} s at {fps} fps is {frames} frames, fewer than the model's window of {window}")
    if frames > MAX_SCENE_FRAMES:
        raise ValueError(f"{seconds} s at {fps} fps is {frames} frames, more than the {MAX_SCENE_FRAMES} a stream "
                         "is judged over (a scene's limit too): judge fewer seconds or frames per second")
    perception = Perception(PerceptionParams.preset(preset))  # type: ignore[arg-type]
    fields: deque[np.ndarray] = deque(maxlen=window)
    window_truth: deque[bool] = deque(maxlen=window)
    called, truth, actions, mixed, slipped_before = [], [], [], [], []
    for frame in islice(SimSensor(None, seed=seed, loop_fps=fps), frames):
        fields.append(perception.step(frame.image)[1].field)
        window_truth.append(frame.truth.is_slip)
        if len(fields) == window:
            called.append(classifier.predict(np.stack(fields), frame.image.shape[1]) >= threshold)
            truth.append(frame.truth.is_slip)
            actions.append(frame.truth.mechanics.command.action)
            mixed.append(len(set(window_truth)) > 1)
            slipped_before.append(not frame.truth.is_slip and any(window_truth))
    called_a, truth_a, mixed_a, before_a = np.array(called), np.array(truth), np.array(mixed), np.array(slipped_before)
    right = called_a == truth_a
    by_action: dict[str, list[int]] = defaultdict(list)
    for i, action in enumerate(actions):
        by_action[action].append(i)
    return {
        "frames_judged": int(right.size),
        "accuracy": float(right.mean()),
        "slip_share": float(truth_a.mean()),
        "held_called_slip": _share(called_a, ~truth_a),
        "slip_called_slip": _share(called_a, truth_a),
        "phases": {action: {"frames": len(rows), "slip_share": float(truth_a[rows].mean()),
                            "accuracy": float(right[rows].mean())} for action, rows in sorted(by_action.items())},
        "transition": {"share": float(mixed_a.mean()), "accuracy": _share(right, mixed_a),
                       "steady_accuracy": _share(right, ~mixed_a), "slip_before_called_slip": _share(called_a, before_a)},
    }


def _share(values: np.ndarray, rows: np.ndarray) -> float | None:
    """Mean of the bool ``values`` (N,) over the bool mask ``rows`` (N,); None when it selects none."""
    return float(values[rows].mean()) if rows.any() else None
