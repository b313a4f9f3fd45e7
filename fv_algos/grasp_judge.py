"""`GraspJudge`: the trial network on a grasp in progress, one camera, frame by frame.

The trial network (:mod:`fv_algos.trial_net`) pools its temporal features over a whole trial.
Online, after every frame, the judge gives P(slip) of the grasp so far: exactly what the network
says of the trial cut at this frame (same descriptors, same pooling), at a cost that does not grow
with the grasp's length. A frame's temporal features depend on the network's ``radius`` (30 for four
layers) frames on each side, so a frame more than ``radius`` frames old is final and only enters a
running sum and maximum; each step recomputes the features of the newest frames from the last
2 * radius + 1 descriptor columns.
"""
from __future__ import annotations

import collections
from pathlib import Path

import numpy as np
import torch

from fv_algos.contact_motion import ContactMotion, ContactMotionParams
from fv_algos.trial_net import TrialNet, descriptor_matrix, field_rows, load_trial_model


class GraspJudge:
    """Running P(slip) of one camera's grasp: ``reset`` when a grasp starts (the next frame is its
    reference), then ``step`` with every frame and its displacement field."""

    def __init__(self, net: TrialNet, params: ContactMotionParams = ContactMotionParams()) -> None:
        self.net = net.eval()
        self.motion = ContactMotion(params)
        self.reset()

    @classmethod
    def from_file(cls, path: str | Path) -> GraspJudge:
        """A judge with the network and contact-motion parameters of a trial model file
        (:func:`fv_algos.trial_net.save_trial_model`); ValueError for any other file."""
        model = load_trial_model(path)
        return cls(model.net, model.params)

    def reset(self) -> None:
        """Forget the grasp: the next ``step`` is the reference frame of a new one."""
        self.frames = 0
        tail = 2 * self.net.radius + 1
        self._series: collections.deque = collections.deque(maxlen=tail)  # (5,) contact-motion rows
        self._rows: collections.deque = collections.deque(maxlen=tail)  # (6,) field rows
        self._final = 0  # frames whose features are final
        self._sum = torch.zeros(self.net.width)  # (width,) sum of the final frames' features
        self._max = torch.full((self.net.width,), -torch.inf)  # (width,) their maximum

    def step(self, image: np.ndarray, field: np.ndarray, valid_share: float) -> float:
        """P(slip) of the grasp up to and including this frame: ``image`` (H, W, 3) BGR uint8,
        ``field`` (h, w, 3) px (dx, dy, |d|; rounded to float16 as in the cached fields the model
        was trained on), ``valid_share`` the share of reference markers valid in this frame."""
        series_row = self.motion.reset(image) if self.frames == 0 else self.motion.step(image)
        return self.push(series_row, field_rows(np.asarray(field, np.float16)[None], np.array([valid_share]))[0])

    @torch.no_grad()
    def push(self, row: np.ndarray, field_row: np.ndarray) -> float:
        """:meth:`step` from a frame's contact-motion row (5,) (``fv_algos.contact_motion.SERIES``)
        and its :func:`fv_algos.trial_net.field_rows` row (6,) (e.g. from cached series and fields)."""
        self._series.append(row)
        self._rows.append(field_row)
        self.frames += 1
        x = descriptor_matrix(np.stack(self._series), np.stack(self._rows))
        h = self.net.features(x[None])[0]  # (width, tail): column j is frame frames - tail + j
        first_column = self.frames - h.shape[1]
        newly_final = self.frames - self.net.radius  # frames [self._final, newly_final) become final
        for frame in range(self._final, max(self._final, newly_final)):
            self._sum += h[:, frame - first_column]
            self._max = torch.maximum(self._max, h[:, frame - first_column])
        self._final = max(self._final, newly_final)
        live = h[:, self._final - first_column:]  # never empty: the newest frame is never final
        peak = torch.maximum(self._max, live.amax(dim=1))
        pooled = torch.cat([(self._sum + live.sum(dim=1)) / self.frames, peak])
        return torch.sigmoid(self.net.logit(pooled)).item()
