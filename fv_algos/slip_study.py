"""Studies over a slip dataset: the paper's Table 1 models, grid resampling, split leakage.

Pure array/torch code for `fv eval`: which predictors make up Table 1 (ConvLSTM, CNN+LSTM,
LSTM, the classical detector), fitting the classical one, cutting a dataset to another grid
size, and a fingerprint that ties a trained model to the exact dataset it saw.
"""
from __future__ import annotations

import hashlib
from dataclasses import replace
from functools import partial

import numpy as np
from scipy import ndimage
from torch import nn

from fv_algos.slip.classical import ClassicalSlipDetector
from fv_algos.slip.classifier import predict_proba
from fv_algos.slip.evaluate import Predictor
from fv_algos.slip.models import count_parameters
from fv_algos.slip.windows import SequenceSet, Split

CLASSICAL = "classical"
CLASSICAL_PARAMS = 1
"""The classical detector learns one number (its threshold; the direction is a sign)."""


def dataset_fingerprint(sequences: SequenceSet) -> str:
    """SHA-256 (first 16 hex digits) over the fields, labels and object ids."""
    digest = hashlib.sha256()
    for array in (sequences.fields, sequences.labels, sequences.object_ids):
        digest.update(np.ascontiguousarray(array).tobytes())
        digest.update(str(array.shape).encode())
    return digest.hexdigest()[:16]


def resample_grid(sequences: SequenceSet, grid: int) -> SequenceSet:
    """The same sequences on a ``grid`` x ``grid`` field (corner-aligned bilinear resampling of
    dx and dy, magnitude recomputed as hypot(dx, dy)); fields (S, F, grid, grid, 3) float16 px.

    Both grids span the reference markers' bounding box with its corners on grid points, so
    this approximates interpolating the markers onto the coarser grid directly.
    """
    if grid < 2:
        raise ValueError(f"grid must be >= 2, got {grid}")
    if grid == sequences.grid:
        return sequences
    dxdy = sequences.fields[..., :2].astype(np.float32)
    factor = grid / sequences.grid  # sets the output size; grid_mode=False maps corner to corner
    out = ndimage.zoom(dxdy, (1, 1, factor, factor, 1), order=1, grid_mode=False)
    fields = np.concatenate([out, np.hypot(out[..., :1], out[..., 1:2])], axis=-1)
    metadata = {**sequences.metadata, "resampled_from_grid": sequences.grid}
    return replace(sequences, fields=fields, metadata=metadata)


def fit_classical(split: Split) -> ClassicalSlipDetector:
    """The classical detector with its threshold fitted on the training windows of ``split``."""
    return ClassicalSlipDetector().fit(split.windows, split.train)


def model_predictor(model: nn.Module) -> tuple[Predictor, int]:
    """(fp32 predictor, trainable parameter count) of a trained model."""
    return partial(predict_proba, model.eval()), count_parameters(model)


def table_predictors(models: dict[str, nn.Module], split: Split) -> dict[str, tuple[Predictor, int]]:
    """Table 1 predictors: each trained model by name, then the classical detector fitted on
    ``split``'s training windows."""
    predictors = {name: model_predictor(model) for name, model in models.items()}
    predictors[CLASSICAL] = (fit_classical(split).predict_proba, CLASSICAL_PARAMS)
    return predictors


def split_inflation(rows: list[dict[str, object]], optimistic: str = "random",
                    honest: str = "sequence") -> dict[str, float]:
    """Per model, accuracy on the ``optimistic`` split minus accuracy on the ``honest`` split
    (Table 1 rows with keys model, split, accuracy); models missing either split are left out."""
    accuracy = {(r["model"], r["split"]): float(r["accuracy"]) for r in rows}  # type: ignore[arg-type]
    return {
        str(model): accuracy[(model, optimistic)] - accuracy[(model, honest)]
        for model, split in accuracy
        if split == optimistic and (model, honest) in accuracy
    }
