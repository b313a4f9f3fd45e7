"""camera_vote: the trial network's answer for all of a grasp's cameras from each camera's P(slip)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fv_algos.camera_vote import LOGIT_LIMIT, camera_vote
from fv_algos.trial_net import DESCRIPTORS, RunningTrial, TrialNet


def test_the_vote_of_each_camera_judged_alone_is_the_network_on_both() -> None:
    torch.manual_seed(0)
    net = TrialNet(hidden=8, layers=3, members=3).eval()
    cameras = [torch.randn(len(DESCRIPTORS), 40) * 3, torch.randn(len(DESCRIPTORS), 55) * 3]
    alone = []
    for x in cameras:
        running = RunningTrial(net)
        alone.append([running.push(x[:, t]) for t in range(x.shape[1])][-1])
    with torch.no_grad():
        both = torch.sigmoid(net(cameras).double()).item()
    assert camera_vote(alone) == pytest.approx(both, abs=1e-6)


def test_the_vote_is_symmetric_and_bounded_at_certain_cameras() -> None:
    assert camera_vote([0.5]) == 0.5 and camera_vote([0.2, 0.2]) == pytest.approx(0.2)
    assert camera_vote([1.0, 0.0]) == 0.5  # +/- LOGIT_LIMIT cancel
    assert camera_vote([1.0, 1.0]) == pytest.approx(1 / (1 + np.exp(-LOGIT_LIMIT)))
    assert camera_vote([0.9, 0.1, 0.9]) == pytest.approx(1 / (1 + np.exp(-np.log(9) / 3)))


def test_a_vote_of_no_camera_is_refused() -> None:
    with pytest.raises(ValueError, match="at least one camera"):
        camera_vote([])
