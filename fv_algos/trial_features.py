"""Trial-level slip classifier from per-frame contact-motion series (image + displacement field).

Physics: slip is the object moving relative to the skin. A GelSight-type image shows two things
that move: the dark markers (the skin) and the shading of the object's imprint. Per frame pair
:class:`ContactMotion` measures, on a small grey image (``size_px``):

- ``marker_px``: mean optical-flow speed of the raw image (dominated by the markers), px/frame at
  ``size_px`` scale;
- ``relative_px``: texture-weighted mean |flow of the marker-free image - flow of the raw image|,
  i.e. imprint motion not explained by skin motion (markers removed by a grey closing of
  ``close_px``), px/frame at ``size_px`` scale;
- ``contact``: mean high-pass energy of the marker-free colour image (imprint shading), grey levels.

:func:`trial_features` turns the series of each camera, together with the marker displacement
field magnitudes of the same frames, into one fixed-length vector per trial (independent of the
trial's length): per camera the features in ``CAMERA_FEATURES``, then their mean, min and max over
the cameras. :class:`TrialLogistic` is an L2-regularised logistic regression on standardised
features (a trial is slip when p >= 0.5; no threshold is tuned).

Features of a whole trial need the trial to end: the decision is per trial (e.g. when the gripper
releases), computed from series that are accumulated online, frame by frame.
"""
from __future__ import annotations

import hashlib
import json
import statistics
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from fv_algos.real_trials import CAMERAS, VIDEO_SUFFIX, Trial, TrialFields, read_frames, write_atomically
from fv_algos.slip.evaluate import classification_metrics
from fv_algos.trial_eval import object_folds

SERIES = ("relative_px", "marker_px", "contact")
CAMERA_FEATURES = (
    "contact_end_rise",  # contact of the last 5 frames minus the trial's least contact
    "contact_range",  # most minus least contact
    "contact_end_share",  # contact of the last 5 frames / most contact
    "relative_ratio_p99",  # 99th percentile of relative_px / (marker_px + 0.2)
    "relative_over_marker_top10",  # mean of the 10 largest relative_px / (same of marker_px + 0.1)
    "marker_p99",  # 99th percentile of marker_px
    "field_end_share",  # mean field |d| of the last 10 frames / its largest value
    "field_log_max",  # log(largest mean field |d| + 0.1 px)
)
KIND = "trial_logistic"
SERIES_CACHE_VERSION = 1


@dataclass(frozen=True)
class ContactMotionParams:
    """size_px: (width, height) the frame is resized to (area averaging). close_px: diameter of the
    grey closing that removes the dark markers (> a marker's diameter at ``size_px``). sigma_px:
    Gaussian high-pass scale of the contact shading. texture_floor: high-pass energy (grey levels,
    summed over BGR) below which a pixel has no imprint texture and gets no weight."""

    size_px: tuple[int, int] = (80, 60)
    close_px: int = 7
    sigma_px: float = 4.0
    texture_floor: float = 4.0


class ContactMotion:
    """Per-frame relative (imprint vs marker) motion and contact energy, online: ``reset`` with the
    reference image, then ``step`` every frame."""

    def __init__(self, params: ContactMotionParams = ContactMotionParams()) -> None:
        self.params = params
        self._kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.close_px, params.close_px))
        self._previous: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _prepare(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(grey (h, w) uint8, marker-free grey (h, w) uint8, texture energy (h, w) float32)."""
        small = cv2.resize(image, self.params.size_px, interpolation=cv2.INTER_AREA)
        closed = cv2.morphologyEx(small, cv2.MORPH_CLOSE, self._kernel)
        closed_f = closed.astype(np.float32)
        texture = np.abs(closed_f - cv2.GaussianBlur(closed_f, (0, 0), self.params.sigma_px)).sum(axis=-1)
        return cv2.cvtColor(small, cv2.COLOR_BGR2GRAY), cv2.cvtColor(closed, cv2.COLOR_BGR2GRAY), texture

    def reset(self, image: np.ndarray) -> np.ndarray:
        """Start from ``image`` (H, W, 3) BGR uint8; returns its row (0, 0, contact) float32."""
        self._previous = self._prepare(image)
        return np.array([0.0, 0.0, self._previous[2].mean()], np.float32)

    def step(self, image: np.ndarray) -> np.ndarray:
        """(relative_px, marker_px, contact) float32 of ``image`` against the previous frame."""
        if self._previous is None:
            return self.reset(image)
        grey, closed, texture = self._prepare(image)
        old_grey, old_closed, old_texture = self._previous
        raw_flow = _flow(old_grey, grey)
        imprint_flow = _flow(old_closed, closed)
        weight = np.clip(np.maximum(texture, old_texture) - self.params.texture_floor, 0.0, None)
        relative = float((np.linalg.norm(imprint_flow - raw_flow, axis=-1) * weight).sum() / (weight.sum() + 1e-6))
        self._previous = (grey, closed, texture)
        return np.array([relative, np.linalg.norm(raw_flow, axis=-1).mean(), texture.mean()], np.float32)


def _flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Farneback optical flow (h, w, 2) px/frame from grey ``a`` to ``b``."""
    return cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 2, 9, 3, 5, 1.1, 0)


def contact_series(frames: Iterable[np.ndarray], params: ContactMotionParams = ContactMotionParams(),
                   reference_frame: int = 1) -> np.ndarray:
    """(F, 3) float32 series (``SERIES``) of BGR ``frames`` from ``reference_frame`` on (the frames
    :func:`fv_algos.real_trials.video_fields` keeps); ValueError when there is no such frame."""
    core, rows = ContactMotion(params), []
    for index, frame in enumerate(frames):
        if index == reference_frame:
            rows.append(core.reset(frame))
        elif index > reference_frame:
            rows.append(core.step(frame))
    if not rows:
        raise ValueError(f"no frame at reference_frame={reference_frame}")
    return np.stack(rows)


def _series_cache_path(cache_dir: Path, video: Path, reference_frame: int, params: ContactMotionParams) -> Path:
    stat = video.stat()
    text = json.dumps([SERIES_CACHE_VERSION, str(video.resolve()), stat.st_size, stat.st_mtime_ns, reference_frame,
                       asdict(params), hashlib.sha256(Path(__file__).read_bytes()).hexdigest()])
    stem = "__".join(video.parts[-3:]).removesuffix(VIDEO_SUFFIX)
    return cache_dir / f"{stem}__contact__{hashlib.sha256(text.encode()).hexdigest()[:16]}.npy"


TrialSeries = dict[tuple[str, str], np.ndarray]


def trial_series(trials: Sequence[Trial], cache_dir: str | Path | None = None, reference_frame: int = 1,
                 params: ContactMotionParams = ContactMotionParams()) -> TrialSeries:
    """:func:`contact_series` of every camera of every trial, keyed (trial name, camera); cached as
    one .npy per video under ``cache_dir`` (None: no cache), keyed by the video, the parameters
    and this module's code."""
    out: TrialSeries = {}
    for trial in trials:
        for cam, video in trial.videos.items():
            cached = None if cache_dir is None else _series_cache_path(Path(cache_dir), video, reference_frame, params)
            if cached is not None and cached.is_file():
                out[(trial.name, cam)] = np.load(cached)
                continue
            try:
                series = contact_series(read_frames(video), params, reference_frame)
            except ValueError as exc:
                raise ValueError(f"{video}: {exc}") from exc
            if cached is not None:
                write_atomically(cached, lambda tmp: np.save(tmp, series))
            out[(trial.name, cam)] = series
    return out


def camera_features(series: np.ndarray, field_magnitude_px: np.ndarray) -> np.ndarray:
    """``CAMERA_FEATURES`` (8,) float64 of one camera: ``series`` (F, 3) from :func:`contact_series`
    and ``field_magnitude_px`` (F,) the mean field |d| per frame (same frames)."""
    relative, marker, contact = (series[:, i].astype(np.float64) for i in range(3))
    magnitude = field_magnitude_px.astype(np.float64)
    return np.array([
        contact[-5:].mean() - contact.min(),
        contact.max() - contact.min(),
        contact[-5:].mean() / max(contact.max(), 1e-6),
        np.percentile(relative / (marker + 0.2), 99),
        np.sort(relative)[-10:].mean() / (np.sort(marker)[-10:].mean() + 0.1),
        np.percentile(marker, 99),
        magnitude[-10:].mean() / (magnitude.max() + 1e-3),
        np.log(magnitude.max() + 0.1),
    ])


def feature_names() -> list[str]:
    """Names of the :func:`trial_features` columns."""
    return [f"{agg}_{name}" for agg in ("mean", "min", "max") for name in CAMERA_FEATURES]


def trial_features(trials: Sequence[Trial], series: TrialSeries, fields: TrialFields,
                   cameras: Sequence[str] = CAMERAS) -> np.ndarray:
    """(n_trials, 24) float64: mean, min and max over the trial's cameras of :func:`camera_features`
    (a trial with one camera repeats it)."""
    rows = []
    for t in trials:
        per = np.stack([camera_features(series[(t.name, c)],
                                        fields[(t.name, c)].fields[..., 2].astype(np.float32).mean(axis=(1, 2)))
                        for c in cameras if (t.name, c) in series])
        rows.append(np.concatenate([per.mean(axis=0), per.min(axis=0), per.max(axis=0)]))
    return np.stack(rows)


@dataclass
class TrialLogistic:
    """Logistic regression on standardised features: p = sigmoid(((x - mean) / std) @ weights + bias).

    mean, std, weights: (D,) float64. l2: penalty (sum of squared weights, per trial).
    """

    mean: np.ndarray
    std: np.ndarray
    weights: np.ndarray
    bias: float
    l2: float = 1.0

    @staticmethod
    def fit(x: np.ndarray, y: np.ndarray, l2: float = 1.0, steps: int = 500, lr: float = 0.5) -> "TrialLogistic":
        """Fit on ``x`` (M, D) and labels ``y`` (M,) 0/1 by full-batch gradient descent."""
        mean, std = x.mean(axis=0), x.std(axis=0) + 1e-9
        z, w, b = (x - mean) / std, np.zeros(x.shape[1]), 0.0
        for _ in range(steps):
            p = 1.0 / (1.0 + np.exp(-(z @ w + b)))
            w -= lr * (z.T @ (p - y) + l2 * w) / len(y)
            b -= lr * float((p - y).mean())
        return TrialLogistic(mean, std, w, b, l2)

    def predict_proba(self, x: np.ndarray) -> np.ndarray:
        """(M,) slip probability of features ``x`` (M, D)."""
        return 1.0 / (1.0 + np.exp(-(((x - self.mean) / self.std) @ self.weights + self.bias)))


def save_trial_model(path: str | Path, model: TrialLogistic, params: ContactMotionParams = ContactMotionParams()) -> Path:
    """Write ``model`` (+ the contact-motion parameters and feature names) as a torch file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"kind": KIND, "features": feature_names(), "params": asdict(params),
                **{k: torch.as_tensor(getattr(model, k)) for k in ("mean", "std", "weights")},
                "bias": model.bias, "l2": model.l2}, path)
    return path


def is_trial_model(path: str | Path) -> bool:
    """Whether ``path`` holds a model written by :func:`save_trial_model`."""
    data = torch.load(path, map_location="cpu", weights_only=False)
    return isinstance(data, dict) and data.get("kind") == KIND


def load_trial_model(path: str | Path) -> tuple[TrialLogistic, ContactMotionParams]:
    """Read a file written by :func:`save_trial_model`; ValueError when it is another kind."""
    data = torch.load(path, map_location="cpu", weights_only=False)
    if not (isinstance(data, dict) and data.get("kind") == KIND):
        raise ValueError(f"{path} is not a trial-level slip model (kind {KIND!r})")
    if data["features"] != feature_names():
        raise ValueError(f"{path}: features {data['features']} differ from this code's {feature_names()}")
    params = data["params"]
    model = TrialLogistic(*(data[k].numpy().astype(np.float64) for k in ("mean", "std", "weights")),
                          float(data["bias"]), float(data["l2"]))
    return model, ContactMotionParams(**{**params, "size_px": tuple(params["size_px"])})


def judge_trials(model: TrialLogistic, x: np.ndarray, labels: np.ndarray) -> dict[str, object]:
    """Trial accuracy, F1, confusion ([[TN, FP], [FN, TP]]), n_trials and probabilities of ``model``
    on features ``x`` (M, D) with ``labels`` (M,) (slip when p >= 0.5)."""
    probability = model.predict_proba(x)
    m = classification_metrics(labels, (probability >= 0.5).astype(np.int64))
    return {"trial_accuracy": m.accuracy, "trial_f1": m.f1, "confusion": [list(r) for r in m.confusion],
            "n_trials": m.n, "probability": probability.tolist()}


def cross_validate_features(x: np.ndarray, labels: np.ndarray, objects: Sequence[str], folds: int, seed: int = 0,
                            l2: float = 1.0) -> dict[str, object]:
    """Object-held-out cross-validation of :class:`TrialLogistic` on trial features ``x`` (M, D):
    ``folds`` object groups (``folds`` = number of objects: leave one object out). Returns {"folds":
    per fold objects, trials, trial accuracy, confusion; "summary": mean, std, min, worst fold,
    pooled accuracy and confusion}."""
    names = np.asarray(objects)
    rows = []
    for k, group in enumerate(object_folds(objects, folds, seed)):
        test = np.isin(names, group)
        model = TrialLogistic.fit(x[~test], labels[~test], l2)
        rows.append({"fold": k, "objects": group, "trials": np.flatnonzero(test).tolist(),
                     **judge_trials(model, x[test], labels[test])})
    accuracy = [r["trial_accuracy"] for r in rows]
    worst = min(rows, key=lambda r: r["trial_accuracy"])
    confusion = np.sum([r["confusion"] for r in rows], axis=0)
    return {"folds": rows, "summary": {
        "trial_accuracy_mean": statistics.fmean(accuracy), "trial_accuracy_std": statistics.pstdev(accuracy),
        "trial_accuracy_min": min(accuracy), "worst_fold": worst["fold"],
        "pooled_trial_accuracy": float(np.trace(confusion) / confusion.sum()), "pooled_confusion": confusion.tolist()}}
