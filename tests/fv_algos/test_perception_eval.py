"""Scoring functions against hand-made truth (arrays only, closed-form answers)."""
from __future__ import annotations

import numpy as np
import pytest

from fv_algos.perception_eval import (
    PerceptionScore,
    grid_points_px,
    identity_swaps,
    marker_pitch_px,
    match_reference,
    score_frame,
    timing_summary_ms,
)
from tests.fv_algos.test_detection import grid_centres

PITCH = 25.0
TRUTH = grid_centres(8, 8, PITCH)


def _score(current: np.ndarray, valid: np.ndarray | None = None, visible: np.ndarray | None = None,
           field: np.ndarray | None = None, true_field: np.ndarray | None = None) -> PerceptionScore:
    """Score a frame whose tracked markers are exactly the truth markers (identity match)."""
    n = len(TRUTH)
    field = np.zeros((4, 2)) if field is None else field
    return score_frame(
        TRUTH, current, np.ones(n, bool) if valid is None else valid, np.arange(n), TRUTH,
        np.ones(n, bool) if visible is None else visible, field, np.zeros_like(field) if true_field is None else true_field,
    )


def test_match_reference_recovers_identities_one_to_one() -> None:
    rng = np.random.default_rng(0)
    order = rng.permutation(len(TRUTH))
    reference = TRUTH[order] + rng.normal(0.0, 0.5, TRUTH.shape)
    reference[0] = TRUTH[order[0]] + 0.4 * PITCH
    match = match_reference(reference, TRUTH, 0.3 * PITCH)
    assert match[0] == -1
    assert np.array_equal(match[1:], order[1:])
    twin = np.vstack([TRUTH[:1], TRUTH[:1] + 0.1])
    assert sorted(match_reference(twin, TRUTH, 0.3 * PITCH).tolist()) == [-1, 0]
    assert (match_reference(np.zeros((0, 2)), TRUTH, 1.0) == -1).all()


def test_identity_swaps_flag_exchanged_markers_only() -> None:
    current = TRUTH + 0.2
    current[[10, 11]] = current[[11, 10]]
    valid = np.ones(len(TRUTH), bool)
    swapped = identity_swaps(current, valid, np.arange(len(TRUTH)), TRUTH)
    assert np.flatnonzero(swapped).tolist() == [10, 11]
    valid[10] = False
    assert np.flatnonzero(identity_swaps(current, valid, np.arange(len(TRUTH)), TRUTH)).tolist() == [11]
    half = TRUTH.copy()
    half[5, 0] += 0.49 * PITCH
    assert not identity_swaps(half, np.ones(len(TRUTH), bool), np.arange(len(TRUTH)), TRUTH).any()


def test_score_frame_closed_form() -> None:
    n = len(TRUTH)
    current = TRUTH + np.array([0.06, 0.08])
    valid = np.ones(n, bool)
    valid[:4] = False
    visible = np.ones(n, bool)
    visible[[0, 10]] = False
    field = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    score = _score(current, valid, visible, field)
    assert score.tracking_rms_px == pytest.approx(0.1)
    assert score.compared == n - 4
    assert score.visible == n - 2
    assert score.tracked == n - 5
    assert score.tracked_share == pytest.approx((n - 5) / (n - 2))
    assert score.field_rmse_px == pytest.approx(0.5)
    assert score.swaps == 0 and score.inconsistent == 0 and score.frames == 1


def test_score_frame_counts_swaps_and_neighbour_flags() -> None:
    current = TRUTH.copy()
    current[[27, 28]] = current[[28, 27]]
    score = _score(current)
    assert score.swaps == 2
    assert score.inconsistent >= 2
    assert score.tracking_rms_px == pytest.approx(np.sqrt(2 * PITCH**2 / len(TRUTH)))


def test_unmatched_markers_are_not_compared_but_truth_stays_visible() -> None:
    n = len(TRUTH)
    match = np.arange(n)
    match[3] = -1
    score = score_frame(TRUTH, TRUTH + 50.0 * (np.arange(n) == 3)[:, None], np.ones(n, bool), match, TRUTH,
                        np.ones(n, bool), np.zeros((1, 2)), np.zeros((1, 2)))
    assert score.tracking_rms_px == 0.0
    assert score.compared == n - 1 and score.visible == n and score.tracked == n - 1


def test_scores_add_up_over_frames() -> None:
    a = _score(TRUTH + np.array([0.3, 0.4]))
    b = _score(TRUTH.copy())
    total = a + b
    assert total.frames == 2 and total.compared == 2 * len(TRUTH)
    assert total.tracking_rms_px == pytest.approx(np.sqrt(0.25 / 2))
    empty = PerceptionScore()
    assert np.isnan(empty.tracking_rms_px) and np.isnan(empty.tracked_share) and np.isnan(empty.field_rmse_px)
    assert (empty + a) == a
    assert sum([a, b], PerceptionScore()) == total


def test_grid_points_follow_the_field_layout() -> None:
    x = np.array([0.0, 10.0, 20.0])
    y = np.array([5.0, 7.0])
    points = grid_points_px(x, y)
    assert points.shape == (6, 2)
    assert np.array_equal(points.reshape(2, 3, 2)[1, 2], [20.0, 7.0])
    with pytest.raises(ValueError, match="1-D"):
        grid_points_px(np.zeros((2, 2)), y)


def test_pitch_and_timing_summary() -> None:
    assert marker_pitch_px(TRUTH) == pytest.approx(PITCH)
    squeezed = TRUTH.copy()
    squeezed[0, 0] += 0.5 * PITCH
    assert marker_pitch_px(squeezed, "min") == pytest.approx(0.5 * PITCH)
    summary = timing_summary_ms(np.arange(1.0, 101.0))
    assert summary["median"] == pytest.approx(50.5)
    assert summary["p99"] == pytest.approx(99.01)
    with pytest.raises(ValueError, match="time sample"):
        timing_summary_ms(np.zeros(0))
    with pytest.raises(ValueError, match=">= 2 points"):
        marker_pitch_px(TRUTH[:1])


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(current=TRUTH[:-1]), "reference_px"),
        (dict(valid=np.ones(3, bool)), "valid"),
        (dict(match=np.full(len(TRUTH), len(TRUTH))), "match indices"),
        (dict(match=np.zeros(len(TRUTH))), "integer array"),
        (dict(current=np.full_like(TRUTH, np.nan)), "non-finite"),
        (dict(true_field=np.zeros((3, 2))), "true_field_px"),
    ],
)
def test_bad_input_is_a_clear_error(change: dict, message: str) -> None:
    n = len(TRUTH)
    args = dict(current=TRUTH, valid=np.ones(n, bool), match=np.arange(n), true_field=np.zeros((4, 2)))
    args.update(change)
    with pytest.raises(ValueError, match=message):
        score_frame(TRUTH, args["current"], args["valid"], args["match"], TRUTH, np.ones(n, bool),
                    np.zeros((4, 2)), args["true_field"])
    with pytest.raises(ValueError, match="max_distance_px"):
        match_reference(TRUTH, TRUTH, 0.0)
