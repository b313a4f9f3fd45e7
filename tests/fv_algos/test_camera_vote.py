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


def test_the_running_vote_leaves_out_cameras_stopped_or_on_an_earlier_grasp() -> None:
    from fv_algos.camera_vote import CameraAnswer, CameraVote
    s = 1_000_000_000
    vote = CameraVote(["left", "right"], stale_after_s=1.0, same_grasp_s=1.0)
    first = vote.update("left", CameraAnswer(1 * s, 0, 1 * s, 0.9))
    assert first.left_out == {"right": "starting"} and first.faults() == {}  # the other camera's first frame is due
    both = vote.update("right", CameraAnswer(1 * s, 0, 1 * s, 0.2))
    assert both.voters == ("left", "right") and both.probability == pytest.approx(camera_vote([0.9, 0.2]))
    reset = vote.update("left", CameraAnswer(3 * s, 3 * s, 3 * s, 0.1))
    assert reset.left_out == {"right": "stale"} and reset.probability == pytest.approx(0.1)
    switching = vote.update("right", CameraAnswer(int(3.1 * s), 0, int(3.1 * s), 0.8))  # its reset frame is due
    assert switching.left_out == {"right": "switching grasp"} and switching.faults() == {}
    assert (switching.first_ns, switching.last_ns) == (3 * s, 3 * s)
    vote.update("left", CameraAnswer(int(4.1 * s), 3 * s, int(4.1 * s), 0.1))
    later = vote.update("right", CameraAnswer(int(4.2 * s), 0, int(4.2 * s), 0.8))  # 1.2 s on, still the old grasp
    assert later.faults() == {"right": "earlier grasp"} and later.probability == pytest.approx(0.1)


def test_a_camera_that_never_answers_is_a_fault_after_stale_after_s() -> None:
    from fv_algos.camera_vote import CameraAnswer, CameraVote
    s = 1_000_000_000
    vote = CameraVote(["left", "right"], stale_after_s=1.0, same_grasp_s=1.0)
    assert vote.update("left", CameraAnswer(1 * s, 0, 1 * s, 0.9)).faults() == {}
    assert vote.update("left", CameraAnswer(int(2.1 * s), 0, int(2.1 * s), 0.9)).faults() == {"right": "no answer yet"}


def test_a_vote_needs_two_different_cameras() -> None:
    from fv_algos.camera_vote import CameraVote
    with pytest.raises(ValueError, match="two or more different names"):
        CameraVote(["left", "left"])
