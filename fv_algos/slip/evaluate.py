"""Evaluation harness: metrics, forward timing and speed/accuracy variants, as table rows.

A *predictor* is any callable windows (B, T, H, W, 3) float32 px -> slip probabilities (B,)
float64 in [0, 1]; torch models (in any variant) and the classical detector are all wrapped as
predictors, so one harness scores them all. Rows are plain dicts, ready for JSON or a table like
the paper's Table 1.
"""
from __future__ import annotations

import copy
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from functools import partial

import numpy as np
import torch
from torch import nn

from fv_algos.slip.classifier import predict_proba
from fv_algos.slip.models import ModelConfig, count_parameters, fast_layout, usable_device
from fv_algos.slip.windows import SequenceSet, Split, WindowSet, make_windows

Predictor = Callable[[np.ndarray], np.ndarray]
VARIANTS = ("fp32", "bf16", "int8", "compile")


@dataclass(frozen=True)
class Metrics:
    """Binary slip metrics. confusion = [[true no-slip, false slip], [missed slip, true slip]]
    (rows: true label 0/1, columns: predicted 0/1); f1 is for the slip class (0.0 when undefined)."""

    accuracy: float
    f1: float
    confusion: tuple[tuple[int, int], tuple[int, int]]
    n: int


def classification_metrics(labels: np.ndarray, predicted: np.ndarray) -> Metrics:
    """Metrics from true and predicted labels, both (N,) in {0, 1}, N >= 1."""
    y, p = np.asarray(labels).astype(np.int64), np.asarray(predicted).astype(np.int64)
    if y.shape != p.shape or y.ndim != 1 or y.size == 0:
        raise ValueError(f"labels and predicted must be equal-length non-empty 1-D arrays, got {y.shape} and {p.shape}")
    if not (np.isin(y, (0, 1)).all() and np.isin(p, (0, 1)).all()):
        raise ValueError("labels and predicted must only hold 0 (no slip) and 1 (slip)")
    conf = np.zeros((2, 2), dtype=np.int64)
    np.add.at(conf, (y, p), 1)
    tp, fp, fn = conf[1, 1], conf[0, 1], conf[1, 0]
    f1 = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 0.0
    return Metrics(float(np.mean(y == p)), float(f1), tuple(map(tuple, conf.tolist())), int(y.size))


def predict_rows(predictor: Predictor, windows: WindowSet, rows: np.ndarray, batch: int = 128) -> np.ndarray:
    """Slip probabilities (N,) of window ``rows``, ``batch`` windows per predictor call."""
    rows = np.asarray(rows)
    return np.concatenate([predictor(windows.get(rows[i : i + batch])[0]) for i in range(0, rows.size, batch)])


def evaluate_rows(predictor: Predictor, windows: WindowSet, rows: np.ndarray) -> Metrics:
    """Metrics of ``predictor`` on window ``rows`` (N,) of ``windows`` (slip when probability >= 0.5)."""
    prob = predict_rows(predictor, windows, rows)
    return classification_metrics(windows.labels[rows], (prob >= 0.5).astype(np.int64))


def evaluate_predictor(predictor: Predictor, split: Split) -> Metrics:
    """Metrics of ``predictor`` on the test side of ``split``."""
    return evaluate_rows(predictor, split.windows, split.test)


def model_windows(sequences: SequenceSet, config: ModelConfig, source: str) -> WindowSet:
    """Every window of ``config.window`` frames (stride 1) of ``sequences``, for a model of ``config``.
    ValueError naming ``source`` (where the sequences came from) when their grid is not the model's,
    they hold fewer frames than its window, or their frames' width (px) is known and not the one the
    model was trained on (its scale_px is in those px)."""
    if sequences.grid != config.grid:
        raise ValueError(f"{source}: fields on a {sequences.grid}x{sequences.grid} grid; the model takes "
                         f"{config.grid}x{config.grid}")
    if sequences.n_frames < config.window:
        raise ValueError(f"{source}: sequences of {sequences.n_frames} frames; the model's window is "
                         f"{config.window} frames")
    width = sequences.frame_width_px
    if width and config.field_width_px and width != config.field_width_px:
        raise ValueError(f"{source}: fields of frames {width} px wide; the model was trained on frames "
                         f"{config.field_width_px} px wide")
    return make_windows(sequences, window=config.window, per_sequence=None)


def time_forward(predictor: Predictor, window: np.ndarray, threads: int, repeats: int = 50, warmup: int = 10) -> float:
    """Median wall time (ms) of one predictor call on ``window`` (1, T, H, W, 3), with torch
    intra-op threads set to ``threads`` (restored afterwards), after ``warmup`` calls."""
    if window.ndim != 5 or window.shape[0] != 1:
        raise ValueError(f"window must have shape (1, T, H, W, 3), got {window.shape}")
    if repeats < 1 or warmup < 0 or threads < 1:
        raise ValueError("repeats and threads must be >= 1 and warmup >= 0")
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for _ in range(warmup):
            predictor(window)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            predictor(window)
            times.append(time.perf_counter() - t0)
    finally:
        torch.set_num_threads(previous)
    return 1e3 * statistics.median(times)


def variant_predictor(model: nn.Module, variant: str = "fp32", device: str = "cpu") -> Predictor:
    """Wrap a model as a predictor in one of VARIANTS, run on ``device`` (a torch device name;
    the windows go in and the probabilities come back as NumPy arrays on the host).

    fp32: as is. bf16: forward under torch.autocast(bfloat16) (convolutions and linear layers in
    bf16) on a channels-last copy of the model. int8: torch.ao.quantization.quantize_dynamic on nn.Linear and nn.LSTM (weights int8,
    activations quantised on the fly); convolutions stay fp32 because dynamic quantisation has no
    conv kernels; CPU only. compile: torch.compile (inductor; needs a C++ compiler on a CPU, Triton
    on a GPU; compiles on first call). ``model`` itself is left on its device.
    """
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    target = usable_device(device)
    if variant == "int8" and target.type != "cpu":
        raise ValueError(f"variant int8 runs on the cpu only, not device {device!r}")
    model = copy.deepcopy(model).to(target).eval()
    if variant == "bf16":
        return partial(predict_proba, fast_layout(model, torch.bfloat16), autocast=torch.bfloat16, device=device)
    if variant == "int8":
        quantized = torch.ao.quantization.quantize_dynamic(model, {nn.Linear, nn.LSTM}, dtype=torch.qint8)
        return partial(predict_proba, quantized)
    if variant == "compile":
        compiled = torch.compile(model)
        compiled.config = model.config
        return partial(predict_proba, compiled, device=device)
    return partial(predict_proba, model, device=device)


def table_rows(
    predictors: dict[str, tuple[Predictor, int]],
    split: Split,
    threads: int = 2,
    repeats: int = 50,
) -> list[dict[str, object]]:
    """One row per named predictor (predictor, parameter count) on ``split``: model, split,
    accuracy, f1, confusion, n, params, ms_per_window (batch 1, median of ``repeats``)."""
    window = split.windows.get(split.test[:1])[0]
    rows = []
    for name, (predictor, params) in predictors.items():
        metrics = evaluate_predictor(predictor, split)
        ms = time_forward(predictor, window, threads, repeats)
        rows.append({"model": name, "split": split.kind, **asdict(metrics), "params": params, "ms_per_window": ms})
    return rows


def variant_rows(
    entries: Sequence[tuple[str, nn.Module, Split]],
    variants: Sequence[str] = VARIANTS,
    threads: int = 2,
    repeats: int = 50,
) -> list[dict[str, object]]:
    """Speed vs accuracy: for each (name, trained model, its split) and each variant, a row with
    model, variant, accuracy, f1, ms_per_window, params, threads. Models with different hidden
    size, window or grid are separate entries (each with a split cut to its window and grid)."""
    rows = []
    for name, model, split in entries:
        window = split.windows.get(split.test[:1])[0]
        for variant in variants:
            predictor = variant_predictor(model, variant)
            metrics = evaluate_predictor(predictor, split)
            rows.append({
                "model": name, "variant": variant, "accuracy": metrics.accuracy, "f1": metrics.f1,
                "ms_per_window": time_forward(predictor, window, threads, repeats),
                "params": count_parameters(model), "threads": threads,
            })
    return rows
