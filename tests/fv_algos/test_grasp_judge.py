"""Online grasp judge: after every frame it gives exactly what the trial network says of the
trial cut at that frame, over grasps longer than its bounded memory, and starts afresh on reset."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from fv_algos.contact_motion import contact_series
from fv_algos.grasp_judge import GraspJudge
from fv_algos.trial_net import TrialNet, TrialNetConfig, descriptor_matrix, field_rows, save_trial_model, trial_probability


def _grasp(frames: int, seed: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Textured BGR frames drifting right, random fields (F, 30, 30, 3) px and valid shares (F,)."""
    rng = np.random.default_rng(seed)
    texture = np.clip(rng.normal(128, 50, (240, 320 + 2 * frames, 3)), 0, 255).astype(np.uint8)
    images = [np.ascontiguousarray(texture[:, 2 * i:2 * i + 320]) for i in range(frames)]
    return images, rng.normal(0, 2, (frames, 30, 30, 3)).astype(np.float32), rng.uniform(0.8, 1.0, frames)


def _offline(net: TrialNet, images: list[np.ndarray], fields: np.ndarray, shares: np.ndarray) -> np.ndarray:
    """(F,) the network on every prefix of the trial, computed whole each time."""
    series = contact_series(images, reference_frame=0)
    rows = field_rows(fields.astype(np.float16), shares, images[0].shape[1])
    return np.array([trial_probability(net, [[descriptor_matrix(series[:k], rows[:k])]])[0]
                     for k in range(1, len(images) + 1)])


@pytest.mark.parametrize("members", [1, 3])
def test_running_probability_equals_the_network_on_every_prefix(members: int) -> None:
    torch.manual_seed(3)
    net = TrialNet(8, members=members)
    images, fields, shares = _grasp(3 * (2 * net.radius + 1), seed=0)  # 87 frames: 3x the judge's memory
    judge = GraspJudge(net)
    online = np.array([judge.step(i, f, s) for i, f, s in zip(images, fields, shares)])
    np.testing.assert_allclose(online, _offline(net, images, fields, shares), atol=1e-5)
    assert judge.frames == len(images)
    judge.reset()  # a new grasp: the second half alone, judged as if it were the whole trial
    again = np.array([judge.step(i, f, s) for i, f, s in zip(images[40:], fields[40:], shares[40:])])
    np.testing.assert_allclose(again, _offline(net, images[40:], fields[40:], shares[40:]), atol=1e-5)


def test_from_file_reads_a_trial_model_and_refuses_other_files(tmp_path: Path) -> None:
    torch.manual_seed(0)
    net = TrialNet(4)
    path = save_trial_model(tmp_path / "trial.pt", net, TrialNetConfig(hidden=4, members=1))
    images, fields, shares = _grasp(5, seed=1)
    judge = GraspJudge.from_file(path)
    online = [judge.step(i, f, s) for i, f, s in zip(images, fields, shares)]
    np.testing.assert_allclose(online, _offline(net.eval(), images, fields, shares), atol=1e-5)
    (tmp_path / "other.pt").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="not a trial-level slip model"):
        GraspJudge.from_file(tmp_path / "other.pt")


def test_a_camera_twice_the_model_rate_is_judged_on_every_other_frame_and_slow_gaps_are_counted() -> None:
    torch.manual_seed(1)
    net = TrialNet(4)
    images, fields, shares = _grasp(20, seed=2)
    judge = GraspJudge(net, fps=25.0, stretch=1.4)
    stamps = np.arange(20) * 20_000_000  # 50 fps
    online = [judge.step(i, f, s) for t, i, f, s in zip(stamps, images, fields, shares) if judge.takes(int(t))]
    np.testing.assert_allclose(online, _offline(net, images[::2], fields[::2], shares[::2]), atol=1e-5)
    assert judge.frames == 10 and judge.slow_gaps == 0
    judge.reset()
    assert [judge.takes(t * 1_000_000) for t in (0, 40, 80, 140, 180)] == [True] * 5  # 60 ms > 1.4 periods
    assert judge.slow_gaps == 1


def test_fields_past_float16_count_as_the_largest_motion_and_non_finite_ones_are_refused(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The float16 cast made 7e4 px inf, whose NaN gradients were then taken as 0: the largest motion
    scored like none. A NaN field scored like no motion."""
    judge = GraspJudge(TrialNet(4))
    rows: list[np.ndarray] = []
    monkeypatch.setattr(judge, "push", lambda row, field_row: rows.append(field_row) or 0.0)
    image = np.full((240, 320, 3), 128, np.uint8)
    for value in (65504.0, 7e4, 1e300):  # float16's largest, and past it
        judge.step(image, np.full((30, 30, 3), value), 1.0)
    assert np.all(np.isfinite(rows)) and rows[0][0] == 65504.0
    np.testing.assert_array_equal(rows[1], rows[0])
    np.testing.assert_array_equal(rows[2], rows[0])
    for bad in (np.nan, np.inf, -np.inf):
        field = np.zeros((30, 30, 3), np.float32)
        field[3, 4, 0] = bad
        with pytest.raises(ValueError, match="field holds 1 non-finite values"):
            judge.step(image, field, 1.0)
    assert len(rows) == 3


@pytest.mark.parametrize("grid", [0, 1, 10])
def test_a_field_of_another_grid_than_the_trained_one_is_refused_by_name(grid: int) -> None:
    """The trial models read 30x30 fields, whose divergence and curl are per grid cell: one rotation of the
    skin read 1.33 on a 10x10 grid against 0.41 on 30x30 (3.2x), taken silently; a 1x1 or 0x0 field raised
    numpy's 'Shape of array too small to calculate a numerical gradient'. Refused now, naming both grids, before the frame changes the judge's state."""
    judge = GraspJudge(TrialNet(4))
    image = np.full((240, 320, 3), 128, np.uint8)
    with pytest.raises(ValueError, match=rf"field grid {grid}x{grid} is not the 30x30 grid"):
        judge.step(image, np.zeros((grid, grid, 3), np.float32), 1.0)
    assert judge.frames == 0
    judge.step(image, np.zeros((30, 30, 3), np.float32), 1.0)
    assert judge.frames == 1
