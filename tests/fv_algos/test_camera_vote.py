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


def _take(vote, camera: str, answer, arrived_s: float):
    """`vote.update` of an answer that arrived at `arrived_s`, the caller's wall clock reading the same."""
    return vote.update(camera, answer, arrived_s, int(arrived_s * 1e9))


def test_the_running_vote_leaves_out_cameras_stopped_or_on_an_earlier_grasp() -> None:
    from fv_algos.camera_vote import CameraAnswer, CameraVote
    s = 1_000_000_000
    vote = CameraVote(["left", "right"], stale_after_s=1.0, same_grasp_s=1.0)
    first = _take(vote, "left", CameraAnswer(1 * s, 0, 1 * s, 0.9), 1.0)
    assert first.left_out == {"right": "starting"} and first.faults() == {}  # the other camera's first frame is due
    both = _take(vote, "right", CameraAnswer(1 * s, 0, 1 * s, 0.2), 1.0)
    assert both.voters == ("left", "right") and both.probability == pytest.approx(camera_vote([0.9, 0.2]))
    reset = _take(vote, "left", CameraAnswer(3 * s, 3 * s, 3 * s, 0.1), 3.0)
    assert reset.left_out == {"right": "stale"} and reset.probability == pytest.approx(0.1)
    switching = _take(vote, "right", CameraAnswer(int(3.1 * s), 0, int(3.1 * s), 0.8), 3.1)  # its reset frame is due
    assert switching.left_out == {"right": "switching grasp"} and switching.faults() == {}
    assert (switching.first_ns, switching.last_ns) == (3 * s, 3 * s)
    _take(vote, "left", CameraAnswer(int(4.1 * s), 3 * s, int(4.1 * s), 0.1), 4.1)
    later = _take(vote, "right", CameraAnswer(int(4.2 * s), 0, int(4.2 * s), 0.8), 4.2)  # 1.2 s on, still the old grasp
    assert later.faults() == {"right": "earlier grasp"} and later.probability == pytest.approx(0.1)


def test_a_camera_that_never_answers_is_a_fault_after_stale_after_s() -> None:
    from fv_algos.camera_vote import CameraAnswer, CameraVote
    s = 1_000_000_000
    vote = CameraVote(["left", "right"], stale_after_s=1.0, same_grasp_s=1.0)
    assert _take(vote, "left", CameraAnswer(1 * s, 0, 1 * s, 0.9), 1.0).faults() == {}
    assert _take(vote, "left", CameraAnswer(int(2.1 * s), 0, int(2.1 * s), 0.9), 2.1).faults() == {"right": "no answer yet"}


def test_staleness_is_judged_by_arrival_not_by_capture_stamps() -> None:
    """A camera whose clock runs 2 s behind counts while its answers arrive (it was left out for good,
    "stale"); one that stops is stale by arrival whatever the stamps say."""
    from fv_algos.camera_vote import CameraAnswer, CameraVote
    s = 1_000_000_000
    vote = CameraVote(["left", "right"], stale_after_s=1.0, same_grasp_s=1.0)
    for k in range(5):
        t = 10.0 + 0.033 * k
        _take(vote, "left", CameraAnswer(int(t * s), int(9.9 * s), int(t * s), 0.05), t)
        both = _take(vote, "right", CameraAnswer(int((t - 2) * s), int(7.9 * s), int((t - 2) * s), 0.95), t)
        assert both.voters == ("left", "right") and both.faults() == {}  # its grasp began 7.9 s by its clock
    alone = _take(vote, "left", CameraAnswer(int(10.2 * s), int(9.9 * s), int(10.2 * s), 0.05), 11.5)
    assert alone.faults() == {"right": "stale"} and alone.probability == pytest.approx(0.05)


def test_cameras_whose_clocks_differ_compare_their_grasps_on_the_callers_clock() -> None:
    """A finger whose clock runs 2 s behind starts its grasps 2 s behind by its stamps too: it was left
    out as on an earlier grasp for good. A reset then starts both fingers' grasps together."""
    from fv_algos.camera_vote import CameraAnswer, CameraVote
    s = 1_000_000_000
    vote = CameraVote(["left", "right"], stale_after_s=1.0, same_grasp_s=1.0)
    for k in range(100):  # 3.3 s of answers
        t = 10.0 + 0.033 * k
        _take(vote, "left", CameraAnswer(int(t * s), int(9.9 * s), int(t * s), 0.05), t + 0.03)
        both = _take(vote, "right", CameraAnswer(int((t - 2) * s), int(7.9 * s), int((t - 2) * s), 0.95), t + 0.05)
        assert both.voters == ("left", "right") and both.left_out == {}, (k, both.left_out)
    reset = _take(vote, "left", CameraAnswer(int(13.4 * s), int(13.4 * s), int(13.4 * s), 0.05), 13.43)
    assert reset.left_out == {"right": "switching grasp"}  # its next frame starts its grasp too
    again = _take(vote, "right", CameraAnswer(int(11.4 * s), int(11.4 * s), int(11.4 * s), 0.95), 13.45)
    assert again.voters == ("left", "right")


def test_an_answer_stamped_ahead_of_every_camera_is_refused() -> None:
    """One answer stamped an hour ahead made the other camera stale; now it is refused, named with its
    offset, and the cameras' next answers count as before. A clock that jumped counts from its next."""
    from fv_algos.camera_vote import CameraAnswer, CameraVote, StampAhead
    s = 1_000_000_000
    vote = CameraVote(["left", "right"], stale_after_s=1.0, same_grasp_s=1.0)
    _take(vote, "left", CameraAnswer(10 * s, 9 * s, 10 * s, 0.1), 10.0)
    _take(vote, "right", CameraAnswer(10 * s, 9 * s, 10 * s, 0.1), 10.0)
    with pytest.raises(StampAhead, match="right: answer stamped 3599.9 s ahead") as err:
        _take(vote, "right", CameraAnswer(3610 * s, 3609 * s, 3610 * s, 0.9), 10.1)
    assert err.value.camera == "right" and err.value.ahead_s == pytest.approx(3600.0 - 0.1)
    after = _take(vote, "left", CameraAnswer(int(10.2 * s), 9 * s, int(10.2 * s), 0.1), 10.2)
    assert after.voters == ("left", "right") and after.probability == pytest.approx(0.1)
    assert _take(vote, "right", CameraAnswer(int(10.3 * s), 9 * s, int(10.3 * s), 0.1), 10.3).faults() == {}


def test_a_stamp_ahead_of_one_clock_only_is_not_refused() -> None:
    """A detector catching up after a stall (its last answer 3 s late, the next on time) is ahead of its
    own last answer, not of the wall clock; cameras on a host whose clock is 5 s ahead of the caller's
    are ahead of the wall clock, not of their own answers (the first is taken by the wall clock alone)."""
    from fv_algos.camera_vote import CameraAnswer, CameraVote, StampAhead
    s = 1_000_000_000
    vote = CameraVote(["left", "right"], stale_after_s=1.0, same_grasp_s=1.0)
    _take(vote, "left", CameraAnswer(7 * s, 0, 7 * s, 0.1), 10.0)
    assert _take(vote, "left", CameraAnswer(int(10.1 * s), 0, int(10.1 * s), 0.1), 10.1).faults() == {}
    ahead = CameraVote(["left", "right"], stale_after_s=1.0, same_grasp_s=1.0)
    with pytest.raises(StampAhead, match="5.0 s ahead"):
        _take(ahead, "left", CameraAnswer(15 * s, 0, 15 * s, 0.1), 10.0)
    for t in (10.1, 10.2):
        _take(ahead, "left", CameraAnswer(int((t + 5) * s), 0, int((t + 5) * s), 0.1), t)
        _take(ahead, "right", CameraAnswer(int((t + 5) * s), 0, int((t + 5) * s), 0.1), t)


def test_a_vote_needs_two_different_cameras() -> None:
    from fv_algos.camera_vote import CameraVote
    with pytest.raises(ValueError, match="two or more different names"):
        CameraVote(["left", "left"])
