"""`GraspJudge`: the trial network on a grasp in progress, one camera, frame by frame.

The trial network (:mod:`fv_algos.trial_net`) pools its temporal features over a whole trial.
Online, after every frame, the judge measures the frame's contact motion and field descriptors
and gives P(slip) of the grasp so far: exactly what the network says of the trial cut at this frame
(same descriptors, same pooling), at a cost that does not grow with the grasp's length
(:class:`fv_algos.trial_net.RunningTrial`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fv_algos.contact_motion import ContactMotion, ContactMotionParams
from fv_algos.trial_net import RunningTrial, TrialNet, descriptor_matrix, field_rows, load_trial_model


class GraspJudge:
    """Running P(slip) of one camera's grasp: ``reset`` when a grasp starts (the next frame is its
    reference), then ``step`` with every frame and its displacement field."""

    def __init__(self, net: TrialNet, params: ContactMotionParams = ContactMotionParams()) -> None:
        self.running = RunningTrial(net)
        self.net = self.running.net
        self.motion = ContactMotion(params)

    @classmethod
    def from_file(cls, path: str | Path) -> GraspJudge:
        """A judge with the network and contact-motion parameters of a trial model file
        (:func:`fv_algos.trial_net.save_trial_model`); ValueError for any other file."""
        model = load_trial_model(path)
        return cls(model.net, model.params)

    def reset(self) -> None:
        """Forget the grasp: the next ``step`` is the reference frame of a new one."""
        self.running.reset()

    @property
    def frames(self) -> int:
        """Frames of the grasp so far."""
        return self.running.frames

    def step(self, image: np.ndarray, field: np.ndarray, valid_share: float) -> float:
        """P(slip) of the grasp up to and including this frame: ``image`` (H, W, 3) BGR uint8,
        ``field`` (h, w, 3) px (dx, dy, |d|; rounded to float16 as in the cached fields the model
        was trained on), ``valid_share`` the share of reference markers valid in this frame."""
        series_row = self.motion.reset(image) if self.frames == 0 else self.motion.step(image)
        return self.push(series_row, field_rows(np.asarray(field, np.float16)[None], np.array([valid_share]))[0])

    def push(self, row: np.ndarray, field_row: np.ndarray) -> float:
        """:meth:`step` from a frame's contact-motion row (5,) (``fv_algos.contact_motion.SERIES``)
        and its :func:`fv_algos.trial_net.field_rows` row (6,) (e.g. from cached series and fields)."""
        return self.running.push(descriptor_matrix(row[None], field_row[None])[:, 0])
