"""`GraspJudge`: the trial network on a grasp in progress, one camera, frame by frame.

The trial network (:mod:`fv_algos.trial_net`) pools its temporal features over a whole trial.
Online, after every frame, the judge measures the frame's contact motion and field descriptors
and gives P(slip) of the grasp so far: exactly what the network says of the trial cut at this frame
(same descriptors, same pooling), at a cost that does not grow with the grasp's length
(:class:`fv_algos.trial_net.RunningTrial`). A camera faster than the model's frame rate has its frames
picked at that rate first (:meth:`GraspJudge.takes`, :mod:`fv_algos.frame_rate`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fv_algos.contact_motion import ContactMotion, ContactMotionParams
from fv_algos.frame_rate import FramePicker
from fv_algos.real_trials import float16_px
from fv_algos.trial_net import RunningTrial, TrialNet, descriptor_matrix, field_rows, load_trial_model

class GraspJudge:
    """Running P(slip) of one camera's grasp: ``reset`` when a grasp starts (the next frame is its
    reference), then for every frame ``takes`` (whether the model judges it: the frames a camera at
    the model's ``fps`` Hz would have filmed) and, when it does, ``step`` with the frame and its
    displacement field. Frames further apart than the model takes (``stretch`` model periods: a slow
    camera or dropped frames) are counted in ``slow_gaps``."""

    def __init__(self, net: TrialNet, params: ContactMotionParams = ContactMotionParams(), fps: float = 25.0,
                 stretch: float = 1.0) -> None:
        self.running = RunningTrial(net)
        self.net = self.running.net
        self.motion = ContactMotion(params)
        self.picker = FramePicker(fps, stretch)

    @classmethod
    def from_file(cls, path: str | Path) -> GraspJudge:
        """A judge with the network, contact-motion parameters, frame rate and training stretch of a
        trial model file (:func:`fv_algos.trial_net.save_trial_model`); ValueError for any other file."""
        model = load_trial_model(path)
        return cls(model.net, model.params, model.fps, model.stretch)

    def reset(self) -> None:
        """Forget the grasp: the next frame is the reference frame of a new one."""
        self.running.reset()
        self.picker.reset()

    def takes(self, stamp_ns: int) -> bool:
        """Whether the frame of ``stamp_ns`` (ns, after the grasp's frames so far) is one the model judges
        (:class:`fv_algos.frame_rate.FramePicker`); the grasp's first frame always is."""
        return self.picker.accept(stamp_ns)

    @property
    def slow_gaps(self) -> int:
        """Frames so far, over every grasp, further apart than ``stretch`` model periods."""
        return self.picker.slow_gaps

    @property
    def frames(self) -> int:
        """Frames of the grasp so far."""
        return self.running.frames

    def step(self, image: np.ndarray, field: np.ndarray, valid_share: float) -> float:
        """P(slip) of the grasp up to and including this frame (one :meth:`takes` kept): ``image`` (H, W, 3) BGR uint8,
        ``field`` (h, w, 3) px of ``image`` (dx, dy, |d|; rounded to float16 as the cached fields the model was
        trained on, :func:`fv_algos.real_trials.float16_px`),
        ``valid_share`` the share of reference markers valid in this frame. ValueError for a field with a NaN or
        infinite value (it would score like no motion) or of another grid than the model's
        (:func:`fv_algos.trial_net.field_rows`), before the frame is taken."""
        values = np.asarray(field)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"field holds {np.count_nonzero(~np.isfinite(values))} non-finite values (NaN or inf)")
        rows = field_rows(float16_px(values)[None], np.array([valid_share]), image.shape[1])
        series_row = self.motion.reset(image) if self.frames == 0 else self.motion.step(image)
        return self.push(series_row, rows[0])

    def push(self, row: np.ndarray, field_row: np.ndarray) -> float:
        """:meth:`step` from a frame's contact-motion row (5,) (``fv_algos.contact_motion.SERIES``)
        and its :func:`fv_algos.trial_net.field_rows` row (6,) (e.g. from cached series and fields)."""
        return self.running.push(descriptor_matrix(row[None], field_row[None])[:, 0])
