"""Slip models, inference (SlipClassifier), the classical detector and the evaluation harness."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from fv_algos.slip.classical import ClassicalConfig, ClassicalSlipDetector, pattern_change, stick_ratio
from fv_algos.slip.classifier import SlipClassifier, predict_proba
from fv_algos.slip.evaluate import (
    classification_metrics,
    evaluate_predictor,
    table_rows,
    time_forward,
    variant_predictor,
    variant_rows,
)
from fv_algos.slip.models import (
    ModelConfig,
    autocast_dtype,
    bf16_fast_on_cpu,
    build_model,
    count_parameters,
    to_model_input,
    usable_device,
    width_gain,
)
from fv_algos.slip.windows import SyntheticConfig, make_windows, split_windows, synthetic_sequences

torch.set_num_threads(1)
SMALL = ModelConfig(hidden=8, window=4, grid=8)


def _model(config: ModelConfig = SMALL, seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return build_model(config).eval()


def test_paper_model_has_exactly_269826_parameters() -> None:
    assert count_parameters(build_model(ModelConfig())) == 269_826
    five = (3 + 64) * 256 * 25 + 256 + 57_600 * 2 + 2
    assert count_parameters(build_model(ModelConfig(kernel=5))) == five


@pytest.mark.parametrize("arch", ["convlstm", "cnn_lstm", "lstm"])
def test_models_map_windows_to_two_logits(arch: str) -> None:
    config = ModelConfig(arch=arch, hidden=8, window=4, grid=12, pool=3)
    x = to_model_input(np.random.default_rng(0).normal(size=(3, 4, 12, 12, 3)).astype(np.float32))
    assert x.shape == (3, 4, 3, 12, 12)
    out = _model(config)(x)
    assert out.shape == (3, 2) and out.dtype == torch.float32
    with pytest.raises(ValueError, match="model input must have shape"):
        _model(config)(x[:, :3])


@pytest.mark.parametrize("arch", ["convlstm", "cnn_lstm", "lstm"])
def test_no_windows_give_no_probabilities(arch: str) -> None:
    """An empty batch raised RuntimeError in the CNN+LSTM's reshape."""
    config = ModelConfig(arch=arch, hidden=8, window=4, grid=12, pool=3)
    prob = predict_proba(_model(config), np.zeros((0, 4, 12, 12, 3), np.float32))
    assert prob.shape == (0,) and prob.dtype == np.float64


def test_convlstm_matches_single_concat_convolution() -> None:
    """The split x/h convolution must equal the textbook conv(concat[x, h]) ConvLSTM."""
    model = _model(ModelConfig(hidden=6, window=5, grid=9, kernel=5))
    x = torch.randn(2, 5, 3, 9, 9) * 4.0
    xs = model.normalise(x)
    h = torch.zeros(2, 6, 9, 9)
    c = torch.zeros_like(h)
    for t in range(5):
        gates = model.gates(torch.cat([xs[:, t], h], dim=1))
        i, f, o, g = torch.chunk(gates, 4, dim=1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h = torch.sigmoid(o) * torch.tanh(c)
    reference = model.head(h.flatten(1))
    with torch.no_grad():
        assert torch.allclose(model(x), reference.detach(), atol=1e-5)


def test_model_config_validation_and_round_trip() -> None:
    with pytest.raises(ValueError, match="arch"):
        ModelConfig(arch="transformer")
    with pytest.raises(ValueError, match="kernel"):
        ModelConfig(kernel=4)
    with pytest.raises(ValueError, match="scale_px"):
        ModelConfig(scale_px=0.0)
    with pytest.raises(ValueError, match="unknown ModelConfig fields"):
        ModelConfig.from_dict({"hidden": 8, "layers": 2})
    for width in (0, 2.5, True):
        with pytest.raises(ValueError, match="field_width_px"):
            ModelConfig(field_width_px=width)  # type: ignore[arg-type]
    config = ModelConfig(hidden=32, window=5, grid=20, field_width_px=640)
    assert ModelConfig.from_dict(config.to_dict()) == config
    assert config.mismatches(ModelConfig()) == ["hidden: 32 != 64", "window: 5 != 10", "grid: 20 != 30",
                                                "field_width_px: 640 != None"]
    # a checkpoint's config from before the frame width was recorded: fields are taken as they come
    old = {k: v for k, v in config.to_dict().items() if k != "field_width_px"}
    assert ModelConfig.from_dict(old).field_width_px is None


def test_fields_are_rescaled_to_the_training_frame_width() -> None:
    """A model trained on 640 px wide frames reads a 320 px camera's field of half the px as the 640 px
    one; a model of no frame width (None), or a camera of unknown width, takes fields as they come."""
    torch.manual_seed(0)
    model = build_model(ModelConfig(hidden=8, window=4, grid=8, field_width_px=640)).eval()
    window = np.random.default_rng(0).normal(0.0, 3.0, (1, 4, 8, 8, 3)).astype(np.float32)
    at_640 = predict_proba(model, window, width_px=640)
    assert predict_proba(model, window / 2, width_px=320) == pytest.approx(at_640, abs=1e-6)
    assert predict_proba(model, window * 2, width_px=1280) == pytest.approx(at_640, abs=1e-6)
    assert predict_proba(model, window, width_px=None) == pytest.approx(at_640, abs=1e-6)
    assert predict_proba(model, window / 2, width_px=None) != pytest.approx(at_640, abs=1e-5)
    assert width_gain(ModelConfig(), 320) == 1.0 and width_gain(model.config, 0) == 1.0


def test_a_negative_frame_width_is_refused() -> None:
    """A gain of -1 from width -640 flipped the field's sign: a mirrored grasp, judged as real."""
    model = build_model(ModelConfig(hidden=8, window=4, grid=8, field_width_px=640)).eval()
    for config in (model.config, ModelConfig()):  # whether or not the model knows its frame width
        with pytest.raises(ValueError, match="width_px must be > 0, or 0 / None when unknown, got -640"):
            width_gain(config, -640)
    with pytest.raises(ValueError, match="width_px"):
        predict_proba(model, np.zeros((1, 4, 8, 8, 3), np.float32), width_px=-640)


@pytest.mark.parametrize("scale", [0.0, 1.0, 1e6, -1e6, 3e38])
def test_probability_is_finite_and_in_unit_interval(scale: float) -> None:
    window = np.full((4, 8, 8, 3), scale, dtype=np.float32)
    window[..., 1] *= -1
    prob = SlipClassifier(_model()).predict(window)
    assert isinstance(prob, float) and 0.0 <= prob <= 1.0


def test_huge_fields_equal_clip_level_fields() -> None:
    """Input is clamped after scaling, so 1e6 px reads exactly like clip * scale_px."""
    model = _model()
    rng = np.random.default_rng(1)
    sign = np.sign(rng.normal(size=(1, 4, 8, 8, 3))).astype(np.float32)
    at_clip = predict_proba(model, sign * SMALL.clip * SMALL.scale_px)
    assert np.allclose(predict_proba(model, sign * 1e6), at_clip, atol=1e-7)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_low_precision_autocast_does_not_overflow(dtype: torch.dtype) -> None:
    model = _model()
    window = np.random.default_rng(2).normal(scale=1e6, size=(2, 4, 8, 8, 3)).astype(np.float32)
    prob = predict_proba(model, window, autocast=dtype)
    assert np.isfinite(prob).all() and ((prob >= 0) & (prob <= 1)).all()
    assert np.allclose(prob, predict_proba(model, window), atol=0.05)


def test_nan_or_bad_shape_raises_clear_error() -> None:
    classifier = SlipClassifier(_model())
    window = np.zeros((4, 8, 8, 3), dtype=np.float32)
    window[1, 2, 3, 0] = np.nan
    with pytest.raises(ValueError, match="1 non-finite"):
        classifier.predict(window)
    window[1, 2, 3, 0] = np.inf
    with pytest.raises(ValueError, match="non-finite"):
        classifier.predict(window)
    with pytest.raises(ValueError, match="shape"):
        classifier.predict(np.zeros((10, 8, 8, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="shape"):
        classifier.predict(np.zeros((8, 8, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="floating point"):
        classifier.predict(np.zeros((4, 8, 8, 3), dtype=np.int32))


def test_precision_names_map_to_autocast_dtypes() -> None:
    assert autocast_dtype("fp32") is None
    assert autocast_dtype("bf16") == torch.bfloat16
    assert autocast_dtype("auto") == (torch.bfloat16 if bf16_fast_on_cpu() else None)
    assert autocast_dtype("auto", "cuda") is None
    with pytest.raises(ValueError, match="precision must be one of"):
        autocast_dtype("fp8")


def test_classifier_precisions_agree() -> None:
    windows = np.random.default_rng(4).normal(scale=3.0, size=(6, 4, 8, 8, 3)).astype(np.float32)
    fp32, bf16 = SlipClassifier(_model(), precision="fp32"), SlipClassifier(_model(), precision="bf16")
    assert fp32.autocast is None and bf16.autocast == torch.bfloat16
    assert SlipClassifier(_model()).autocast == autocast_dtype("auto")
    for window in windows:
        assert bf16.predict(window) == pytest.approx(fp32.predict(window), abs=0.05)


def test_devices_are_refused_by_name_and_reason() -> None:
    assert usable_device("cpu") == torch.device("cpu")
    for bad in ("gpu", "cuda:x"):
        with pytest.raises(ValueError, match=f"device '{bad}' is not a torch device"):
            usable_device(bad)
    if torch.cuda.is_available():
        assert usable_device("cuda").type == "cuda"
        with pytest.raises(ValueError, match=f"cuda device\\(s\\), numbered from 0"):
            usable_device(f"cuda:{torch.cuda.device_count()}")
    else:  # torch itself raises AssertionError, at the first tensor moved
        with pytest.raises(ValueError, match="device 'cuda:0' is not usable here: this torch .* sees no cuda device"):
            usable_device("cuda:0")
        with pytest.raises(ValueError, match="device 'cuda' is not usable here"):
            SlipClassifier(_model(), device="cuda")
        with pytest.raises(ValueError, match="device 'cuda' is not usable here"):
            variant_predictor(_model(), "fp32", "cuda")
    with pytest.raises(ValueError, match="int8 runs on the cpu only|not usable here"):
        variant_predictor(_model(), "int8", "cuda")


def test_warm_up_runs_one_window_and_changes_no_answer() -> None:
    window = np.random.default_rng(5).normal(scale=3.0, size=(4, 8, 8, 3)).astype(np.float32)
    classifier = SlipClassifier(_model())
    before = classifier.predict(window)
    assert classifier.warm_up() > 0
    assert classifier.predict(window) == before


def test_classifier_rejects_model_with_other_config() -> None:
    with pytest.raises(ValueError, match="hidden: 8 != 16"):
        SlipClassifier(_model(), expected=ModelConfig(hidden=16, window=4, grid=8))


def test_metrics_closed_form() -> None:
    m = classification_metrics(np.array([0, 0, 1, 1, 1]), np.array([0, 1, 1, 1, 0]))
    assert m.confusion == ((1, 1), (1, 2))
    assert m.accuracy == pytest.approx(3 / 5)
    assert m.f1 == pytest.approx(2 * 2 / (2 * 2 + 1 + 1))
    assert classification_metrics(np.array([0, 0]), np.array([0, 0])).f1 == 0.0
    with pytest.raises(ValueError, match="only hold 0"):
        classification_metrics(np.array([0, 2]), np.array([0, 1]))
    with pytest.raises(ValueError, match="equal-length"):
        classification_metrics(np.array([0, 1]), np.array([0]))


def _pattern_windows() -> tuple[np.ndarray, np.ndarray]:
    """Two windows (T=6, 8x8): a fixed pattern growing (stick) and a translating one (slip)."""
    yy, xx = np.mgrid[0:8, 0:8].astype(np.float64)
    frames_stick, frames_slip = [], []
    for t in range(6):
        frames_stick.append(np.sin(xx / 2.0) * np.cos(yy / 3.0) * (1 + t))
        frames_slip.append(np.sin((xx - 1.5 * t) / 2.0) * np.cos(yy / 3.0) * 3)
    out = []
    for frames in (frames_stick, frames_slip):
        d = np.stack(frames)[..., None] * np.array([2.0, 1.0])
        out.append(np.concatenate([d, np.hypot(d[..., :1], d[..., 1:])], axis=-1))
    return np.stack(out).astype(np.float32), np.array([0, 1])


def test_classical_features_separate_stick_from_slip() -> None:
    windows, _ = _pattern_windows()
    change = pattern_change(windows)
    assert change[0] < 1e-6 and change[1] > 0.3
    ratio = stick_ratio(windows)
    assert ratio[0] == 1.0 and ratio[1] < 0.6
    assert pattern_change(np.zeros_like(windows)).tolist() == [0.0, 0.0]
    with pytest.raises(ValueError, match="non-finite"):
        pattern_change(np.full_like(windows, np.nan))


@pytest.mark.parametrize("scale", [1e-170, 1e160, 1e300])
def test_classical_features_hold_at_extreme_scales(scale: float) -> None:
    """A window of 1e160 px overflowed the Gram matrix: numpy's eigh raised LinAlgError."""
    windows, _ = _pattern_windows()
    windows = windows.astype(np.float64) * 3.0  # well above the 0.2 px noise floor
    change, ratio = pattern_change(windows * scale), stick_ratio(windows * scale)
    if scale < 1:  # far below the noise floor: no motion, every cell sticks
        assert change.tolist() == [0.0, 0.0] and ratio.tolist() == [1.0, 1.0]
    else:  # the noise floor no longer counts: the shares of the same windows without it
        assert change == pytest.approx(pattern_change(windows, noise_floor_px=1e-300))
        assert ratio.tolist() == stick_ratio(windows, noise_floor_px=1e-300).tolist()


@pytest.mark.parametrize("feature", ["pattern_change", "stick_ratio"])
def test_classical_detector_fits_threshold(feature: str) -> None:
    windows, labels = _pattern_windows()
    detector = ClassicalSlipDetector(ClassicalConfig(feature=feature))
    with pytest.raises(ValueError, match="not fitted"):
        detector.predict_proba(windows)
    detector.fit_features(detector.features(windows), labels)
    assert detector.predict_proba(windows).tolist() == [0.0, 1.0]
    assert detector.slip_above == (feature == "pattern_change")


def test_threshold_fit_is_optimal_on_overlapping_scores() -> None:
    values = np.array([0.1, 0.2, 0.3, 0.35, 0.4, 0.8, 0.9])
    labels = np.array([0, 0, 1, 0, 1, 1, 1])
    detector = ClassicalSlipDetector().fit_features(values, labels)
    assert detector.slip_above and 0.2 < detector.threshold < 0.3
    flipped = ClassicalSlipDetector().fit_features(-values, labels)
    assert not flipped.slip_above


@pytest.fixture(scope="module")
def small_split():
    sequences = synthetic_sequences(40, SyntheticConfig(grid=8, n_frames=6), seed=5)
    return split_windows(make_windows(sequences, window=4, per_sequence=2), "sequence", 0.25, seed=0)


def test_harness_rows_for_models_and_classical(small_split) -> None:
    model = _model()
    detector = ClassicalSlipDetector().fit(small_split.windows, small_split.train)
    rows = table_rows(
        {"convlstm": (variant_predictor(model), count_parameters(model)), "classical": (detector.predict_proba, 0)},
        small_split, threads=1, repeats=3,
    )
    assert [r["model"] for r in rows] == ["convlstm", "classical"]
    for row in rows:
        assert 0.0 <= row["accuracy"] <= 1.0 and row["ms_per_window"] > 0 and row["split"] == "sequence"
        assert sum(map(sum, row["confusion"])) == small_split.test.size
    assert rows[1]["accuracy"] > 0.6  # the feature carries signal on synthetic slips


def test_variants_agree_with_fp32(small_split) -> None:
    model = _model()
    window = small_split.windows.get(small_split.test[:8])[0]
    reference = variant_predictor(model, "fp32")(window)
    for variant in ("bf16", "int8"):
        assert np.allclose(variant_predictor(model, variant)(window), reference, atol=0.05), variant
    rows = variant_rows([("tiny", model, small_split)], variants=("fp32", "int8"), threads=1, repeats=3)
    assert [r["variant"] for r in rows] == ["fp32", "int8"]
    assert rows[0]["accuracy"] == evaluate_predictor(variant_predictor(model), small_split).accuracy
    with pytest.raises(ValueError, match="variant"):
        variant_predictor(model, "fp8")


def test_time_forward_validates_and_restores_threads() -> None:
    before = torch.get_num_threads()
    ms = time_forward(variant_predictor(_model()), np.zeros((1, 4, 8, 8, 3), np.float32), threads=2, repeats=5, warmup=1)
    assert ms > 0 and torch.get_num_threads() == before
    with pytest.raises(ValueError, match="window must have shape"):
        time_forward(variant_predictor(_model()), np.zeros((2, 4, 8, 8, 3), np.float32), threads=1)


def test_cross_entropy_gradient_reaches_all_parameters() -> None:
    model = _model().train()
    x = to_model_input(np.random.default_rng(3).normal(size=(4, 4, 8, 8, 3)).astype(np.float32))
    F.cross_entropy(model(x), torch.tensor([0, 1, 0, 1])).backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0 for p in model.parameters())
