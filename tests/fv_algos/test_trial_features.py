"""Trial-level slip features: contact motion against closed-form motions, features, the logistic
model, its file and object-held-out cross-validation (no data needed)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from fv_algos.trial_features import (
    CAMERA_FEATURES,
    ContactMotion,
    TrialLogistic,
    camera_features,
    cross_validate_features,
    feature_names,
    is_trial_model,
    load_trial_model,
    save_trial_model,
)


def _scene(imprint_shift_px: int, marker_shift_px: int) -> np.ndarray:
    """320x240 BGR: a textured imprint (shifted right by ``imprint_shift_px``) under a grid of dark
    markers (shifted right by ``marker_shift_px``)."""
    texture = cv2.GaussianBlur(np.random.default_rng(0).uniform(0, 255, (240, 400)).astype(np.float32), (0, 0), 6)
    texture = 60 + 3.0 * (texture - texture.mean())
    image = np.repeat(texture[:, 40 - imprint_shift_px: 360 - imprint_shift_px, None], 3, axis=2)
    image = np.clip(image, 0, 255).astype(np.uint8)
    for y in range(20, 240, 40):
        for x in range(20, 320, 40):
            cv2.circle(image, (x + marker_shift_px, y), 6, (0, 0, 0), -1)
    return image


def test_relative_motion_is_small_when_imprint_sticks_and_large_when_it_slips() -> None:
    stick, slip = ContactMotion(), ContactMotion()
    stick.reset(_scene(0, 0))
    slip.reset(_scene(0, 0))
    relative_stick, marker_stick, _ = stick.step(_scene(8, 8))  # skin and imprint move together
    relative_slip, marker_slip, _ = slip.step(_scene(8, 0))  # imprint moves, markers stay
    assert marker_stick > 1.0
    assert relative_slip > 3 * relative_stick


def test_camera_features_closed_form() -> None:
    series = np.zeros((20, 3), np.float32)
    series[:, 2] = np.r_[np.full(15, 4.0), np.full(5, 2.0)]  # contact drops to half at the end
    magnitude = np.r_[np.zeros(10), np.full(10, 3.0)]
    f = dict(zip(CAMERA_FEATURES, camera_features(series, magnitude)))
    assert f["contact_end_rise"] == pytest.approx(0.0) and f["contact_range"] == pytest.approx(2.0)
    assert f["contact_end_share"] == pytest.approx(0.5)
    assert f["field_end_share"] == pytest.approx(3.0 / 3.001) and f["field_log_max"] == pytest.approx(np.log(3.1))
    assert len(feature_names()) == 3 * len(CAMERA_FEATURES)


def test_logistic_model_file_and_object_held_out_cv(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    labels = np.repeat([0, 1], 30)
    x = rng.normal(size=(60, len(feature_names())))
    x[:, 0] += 4.0 * labels  # one informative feature
    objects = [f"o{i % 10}" for i in range(60)]
    report = cross_validate_features(x, labels, objects, folds=10)
    assert report["summary"]["trial_accuracy_min"] >= 0.8 and len(report["folds"]) == 10
    for fold in report["folds"]:  # every test object is absent from its fold's training trials
        assert {objects[i] for i in fold["trials"]} == set(fold["objects"])
    model = TrialLogistic.fit(x, labels)
    path = save_trial_model(tmp_path / "m.pt", model)
    assert is_trial_model(path)
    again, params = load_trial_model(path)
    np.testing.assert_allclose(again.predict_proba(x), model.predict_proba(x))
    assert params.size_px == (80, 60)
