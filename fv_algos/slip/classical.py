"""A non-learned slip detector: one scalar feature per window and a threshold fitted on training data.

Both features come from the best fixed-pattern (rank-1) model of a window: while the contact
sticks, the skin's displacement pattern keeps its shape and only its amplitude changes,
d_t(cell) ~ a_t * P(cell); once it slips the pattern translates, rotates or decorrelates.

- "pattern_change": fraction of the window's dx/dy energy that no fixed pattern explains,
  (sum(lambda) - max(lambda)) / (sum(lambda) + E_noise), lambda the eigenvalues of the T x T Gram
  matrix of the frames, E_noise = noise_floor_px**2 * (values in the window). High = slip.
- "stick_ratio" (after the stick-region ratio of Dong et al.): fraction of grid cells whose
  displacement history the fixed pattern explains to within ``stick_tol`` of the cell's RMS
  displacement plus ``noise_floor_px``. Low = slip.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fv_algos.slip.windows import WindowSet

FEATURES = ("pattern_change", "stick_ratio")


@dataclass(frozen=True)
class ClassicalConfig:
    """feature: one of FEATURES. noise_floor_px: displacement noise level (px) below which motion
    is ignored. stick_tol: relative residual under which a cell counts as sticking."""

    feature: str = "pattern_change"
    noise_floor_px: float = 0.2
    stick_tol: float = 0.25

    def __post_init__(self) -> None:
        if self.feature not in FEATURES:
            raise ValueError(f"ClassicalConfig.feature must be one of {FEATURES}, got {self.feature!r}")
        if not self.noise_floor_px > 0 or not self.stick_tol > 0:
            raise ValueError("ClassicalConfig.noise_floor_px and stick_tol must be > 0")


def _frames(windows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, T, H, W, 3) px -> the (N, T, H*W*2) float64 dx/dy values of each window divided by its
    largest |value|, and those scales (N,) px (1 for an all-zero window); ValueError on bad input.
    Both features are ratios, so they are computed on the scaled values (the noise floor scaled
    alike): the Gram matrix of a window of 1e160 px no longer overflows."""
    arr = np.asarray(windows)
    if arr.ndim != 5 or arr.shape[-1] != 3:
        raise ValueError(f"windows must have shape (N, T, H, W, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError("windows contain non-finite values (NaN/inf)")
    frames = arr[..., :2].reshape(arr.shape[0], arr.shape[1], -1).astype(np.float64)
    scale = np.abs(frames).max(axis=(1, 2), initial=0.0)
    scale[scale == 0] = 1.0
    return frames / scale[:, None, None], scale


def _rank1(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (N, T) ascending and top unit eigenvector (N, T) of each window's Gram matrix."""
    gram = frames @ frames.transpose(0, 2, 1)
    values, vectors = np.linalg.eigh(gram)
    return np.clip(values, 0.0, None), vectors[:, :, -1]


def pattern_change(windows: np.ndarray, noise_floor_px: float = 0.2) -> np.ndarray:
    """(N, T, H, W, 3) px -> (N,) float64 in [0, 1): unexplained-by-a-fixed-pattern energy share."""
    frames, scale = _frames(windows)
    values, _ = _rank1(frames)
    total = values.sum(axis=1)
    with np.errstate(over="ignore"):  # a window far below the noise floor: an infinite noise term, share 0
        noise = (noise_floor_px / scale) ** 2 * frames.shape[1] * frames.shape[2]
    return (total - values[:, -1]) / (total + noise)


def stick_ratio(windows: np.ndarray, noise_floor_px: float = 0.2, stick_tol: float = 0.25) -> np.ndarray:
    """(N, T, H, W, 3) px -> (N,) float64 in [0, 1]: share of cells following the fixed pattern."""
    frames, scale = _frames(windows)
    _, top = _rank1(frames)
    residual = frames - top[:, :, None] * np.einsum("nt,ntk->nk", top, frames)[:, None, :]
    n, t = frames.shape[:2]
    cell_res = np.sqrt((residual.reshape(n, t, -1, 2) ** 2).mean(axis=(1, 3)))
    cell_rms = np.sqrt((frames.reshape(n, t, -1, 2) ** 2).mean(axis=(1, 3)))
    with np.errstate(over="ignore"):
        floor = noise_floor_px / scale[:, None]
    return (cell_res <= stick_tol * cell_rms + floor).mean(axis=1)


class ClassicalSlipDetector:
    """Threshold on one feature; ``fit`` picks the threshold and its direction that maximise
    training accuracy."""

    def __init__(self, config: ClassicalConfig = ClassicalConfig()) -> None:
        self.config = config
        self.threshold: float | None = None
        self.slip_above = True

    def features(self, windows: np.ndarray) -> np.ndarray:
        """(N, T, H, W, 3) px -> (N,) float64 feature values."""
        if self.config.feature == "pattern_change":
            return pattern_change(windows, self.config.noise_floor_px)
        return stick_ratio(windows, self.config.noise_floor_px, self.config.stick_tol)

    def fit_features(self, values: np.ndarray, labels: np.ndarray) -> ClassicalSlipDetector:
        """Fit on precomputed feature values (N,) and labels (N,) in {0, 1}."""
        values, labels = np.asarray(values, dtype=np.float64), np.asarray(labels)
        if values.shape != labels.shape or values.ndim != 1 or values.size == 0:
            raise ValueError(f"values and labels must be equal-length 1-D arrays, got {values.shape} and {labels.shape}")
        order = np.argsort(values, kind="stable")
        v, y = values[order], labels[order]
        # accuracy of "slip if value > threshold" for a threshold after each sorted position
        below_neg = np.concatenate([[0], np.cumsum(y == 0)])
        above_pos = np.count_nonzero(y == 1) - np.concatenate([[0], np.cumsum(y == 1)])
        acc_above = (below_neg + above_pos) / y.size
        cuts = np.concatenate([[v[0] - 1.0], (v[:-1] + v[1:]) / 2.0, [v[-1] + 1.0]])
        best_above, best_below = int(np.argmax(acc_above)), int(np.argmin(acc_above))
        self.slip_above = acc_above[best_above] >= 1.0 - acc_above[best_below]
        self.threshold = float(cuts[best_above if self.slip_above else best_below])
        return self

    def fit(self, windows: WindowSet, rows: np.ndarray, chunk: int = 256) -> ClassicalSlipDetector:
        """Fit on window rows of a :class:`WindowSet`, ``chunk`` windows at a time."""
        rows = np.asarray(rows)
        values = np.concatenate([self.features(windows.get(rows[i : i + chunk])[0]) for i in range(0, rows.size, chunk)])
        return self.fit_features(values, windows.labels[rows])

    def predict_proba(self, windows: np.ndarray) -> np.ndarray:
        """(N, T, H, W, 3) px -> (N,) float64 hard decisions 0.0 / 1.0 (slip)."""
        if self.threshold is None:
            raise ValueError("ClassicalSlipDetector is not fitted; call fit() first")
        values = self.features(windows)
        slip = values > self.threshold if self.slip_above else values <= self.threshold
        return slip.astype(np.float64)
