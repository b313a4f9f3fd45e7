"""Slip classifiers on real trials: windows, object-held-out cross-validation, trial decisions.

Every camera of every trial is one sequence of a :class:`SequenceSet` (zero-padded to the longest
video; windows never reach into the padding). Windows of ``window`` frames start every
``stride`` frames.

Window labels (see also :mod:`fv_algos.real_trials`): a window is *active* when its activity
(mean over the window's frame pairs and the grid of |change of (dx, dy)| between consecutive
frames, px/frame) is at least ``activity_px``. Training and window-level accuracy use every
window of a no-slip trial (label 0) and the active windows of a slip trial (label 1); the
inactive windows of a slip trial are left out (they may precede the slip). Slip windows are
repeated so that both classes are equally frequent in training.

Trial decision: the trial's score is the mean of the ``top_k`` highest slip probabilities over
all its windows, both cameras pooled; the trial is slip when the score is at least the
threshold. The threshold is chosen on the training trials only (the midpoint of the widest gap
that maximises training trial accuracy), never on the trials being judged.

Cross-validation keeps each object on one side: the objects are dealt into ``folds`` groups of
about equal trial count, and each fold's model never sees its test objects.
"""
from __future__ import annotations

import multiprocessing
import statistics
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from functools import partial
from typing import TypeVar

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from fv_algos.allocator import steady_malloc
from fv_algos.real_trials import CAMERAS, FIELD_WIDTH_PX, Trial, TrialFields, at_reference_width, require_frames
from fv_algos.slip.classifier import load_checkpoint, predict_proba
from fv_algos.slip.evaluate import classification_metrics, predict_rows
from fv_algos.slip.models import ModelConfig
from fv_algos.slip.train import TrainConfig, train
from fv_algos.slip.windows import SequenceSet, Split, WindowSet

MONITOR_WINDOWS = 256
Item = TypeVar("Item")
Result = TypeVar("Result")


@dataclass(frozen=True)
class TrialRule:
    """Window cutting, window labels and trial decisions.

    stride: frames between window starts. activity_px: activity (px/frame) from which a window
    of a slip trial counts as slip. top_k: windows averaged for the trial score.
    """

    stride: int = 5
    activity_px: float = 0.3
    top_k: int = 3

    def __post_init__(self) -> None:
        if self.stride < 1 or self.top_k < 1 or not self.activity_px >= 0.0:
            raise ValueError(f"TrialRule needs stride >= 1, top_k >= 1, activity_px >= 0, got {self}")


@dataclass
class TrialWindows:
    """All windows of a set of trials.

    windows: the :class:`WindowSet` (sequence = one camera of one trial).
    trial: (N,) int64 index into ``trials`` of each window. activity: (N,) float32 px/frame.
    labelled: (N,) bool, the window has a label under the rule (used for training and
    window accuracy). trial_labels: (n_trials,) int64. objects: (n_trials,) object names.
    """

    windows: WindowSet
    trial: np.ndarray
    activity: np.ndarray
    labelled: np.ndarray
    trial_labels: np.ndarray
    objects: list[str]

    @property
    def labels(self) -> np.ndarray:
        """(N,) int64 label of each window (its trial's label)."""
        return self.windows.labels


def window_activity(fields: np.ndarray, window: int, starts: np.ndarray) -> np.ndarray:
    """Activity (px/frame) of windows of ``window`` frames starting at ``starts`` (M,) in one
    video's fields (F, H, W, 3): mean over the window's F-1 frame pairs and the grid of the
    Euclidean change of (dx, dy). Returns (M,) float32."""
    steps = np.linalg.norm(np.diff(fields[..., :2].astype(np.float32), axis=0), axis=-1).mean(axis=(1, 2))  # (F-1,)
    cumulative = np.concatenate([[0.0], np.cumsum(steps)])
    return ((cumulative[starts + window - 1] - cumulative[starts]) / max(window - 1, 1)).astype(np.float32)


def trial_windows(
    trials: Sequence[Trial], fields: TrialFields, window: int, rule: TrialRule, cameras: Sequence[str] = CAMERAS
) -> TrialWindows:
    """Cut the windows of every available camera of every trial, fields in px of the frame at
    ``FIELD_WIDTH_PX`` wide; ValueError naming the videos shorter than ``window`` (they would give
    none, and their trial no score)."""
    require_frames({(t.name, c): fields[(t.name, c)] for t in trials for c in cameras if (t.name, c) in fields}, window)
    videos = [(i, at_reference_width(fields[(t.name, c)].fields, fields[(t.name, c)].width_px))
              for i, t in enumerate(trials) for c in cameras if (t.name, c) in fields]
    longest = max(v.shape[0] for _, v in videos)
    grid = videos[0][1].shape[1]
    padded = np.zeros((len(videos), longest, grid, grid, 3), np.float16)
    names = sorted({t.object for t in trials})
    labels = np.array([trials[i].label for i, _ in videos])
    object_ids = np.array([names.index(trials[i].object) for i, _ in videos])
    seq, start, trial, activity = [], [], [], []
    for s, (i, video) in enumerate(videos):
        padded[s, : video.shape[0]] = video
        starts = np.arange(0, video.shape[0] - window + 1, rule.stride)
        seq.append(np.full(starts.size, s))
        start.append(starts)
        trial.append(np.full(starts.size, i))
        activity.append(window_activity(video, window, starts))
    sequences = SequenceSet(padded, labels, object_ids,
                            {"source": "real trials", "stride": rule.stride, "frame_width_px": FIELD_WIDTH_PX})
    windows = WindowSet(sequences, window, np.concatenate(seq).astype(np.int64), np.concatenate(start).astype(np.int64))
    act = np.concatenate(activity)
    return TrialWindows(
        windows,
        np.concatenate(trial).astype(np.int64),
        act,
        (windows.labels == 0) | (act >= rule.activity_px),
        np.array([t.label for t in trials], np.int64),
        [t.object for t in trials],
    )


def balanced_rows(rows: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """``rows`` with the rows of the rarer class repeated (cycled) until both classes are equally
    frequent; ``labels`` are the labels of ``rows``."""
    by_class = [rows[labels == c] for c in (0, 1)]
    if min(r.size for r in by_class) == 0:
        raise ValueError("training windows hold only one class")
    n = max(r.size for r in by_class)
    return np.concatenate([np.resize(r, n) for r in by_class])


def trial_scores(probability: np.ndarray, trial: np.ndarray, n_trials: int, top_k: int) -> np.ndarray:
    """Mean of the ``top_k`` highest window probabilities (N,) of each trial -> (n_trials,)
    float64 (NaN for a trial with no window)."""
    scores = np.full(n_trials, np.nan)
    for i in np.unique(trial):
        p = np.sort(probability[trial == i])[::-1]
        scores[i] = float(p[:top_k].mean())
    return scores


def choose_threshold(scores: np.ndarray, labels: np.ndarray) -> float:
    """Threshold on trial ``scores`` (M,) maximising accuracy on ``labels`` (M,); among equally
    accurate cuts the one in the widest gap between consecutive scores, at its midpoint."""
    values = np.unique(scores)
    cuts = np.concatenate([[values[0] - 1e-6], (values[:-1] + values[1:]) / 2, [values[-1] + 1e-6]])
    gaps = np.concatenate([[0.0], np.diff(values), [0.0]])
    accuracy = np.array([np.mean((scores >= c) == labels) for c in cuts])
    best = np.flatnonzero(accuracy == accuracy.max())
    return float(np.clip(cuts[best[np.argmax(gaps[best])]], 0.0, 1.0))


def object_folds(objects: Sequence[str], folds: int, seed: int = 0) -> list[list[str]]:
    """Deal the distinct ``objects`` (one entry per trial) into ``folds`` groups of about equal
    trial count (objects shuffled with ``seed``, then largest first into the emptiest group)."""
    names, counts = np.unique(np.asarray(objects), return_counts=True)
    if not 2 <= folds <= names.size:
        raise ValueError(f"folds must be in [2, {names.size}] (the number of objects), got {folds}")
    order = np.random.default_rng(seed).permutation(names.size)
    order = order[np.argsort(-counts[order], kind="stable")]
    groups: list[list[str]] = [[] for _ in range(folds)]
    load = np.zeros(folds)
    for k in order:
        g = int(np.argmin(load))
        groups[g].append(str(names[k]))
        load[g] += counts[k]
    return [sorted(g) for g in groups]


@dataclass(frozen=True)
class FitConfig:
    """Model, training and decision settings for real trials (``train.steps`` optimizer steps)."""

    train: TrainConfig
    rule: TrialRule = TrialRule()


def fit_train_config(config: FitConfig, init: str | None) -> TrainConfig:
    """The training config of a fit: ``config.train``, or to fine-tune the checkpoint ``init``, its architecture
    (in place of ``config.train.model``) and ``config.train.steps`` more optimizer steps than it was trained for."""
    if init is None:
        return config.train
    start = load_checkpoint(init)
    return replace(config.train, model=start.model_config, steps=start.step + config.train.steps)


def fit(data: TrialWindows, train_trials: np.ndarray, config: FitConfig, monitor: np.ndarray | None = None,
        init: str | None = None) -> tuple[nn.Module, float, dict[str, object]]:
    """Train on the labelled windows of ``train_trials`` (trial indices) and choose the trial
    threshold on those trials. ``monitor``: window rows scored during training (default: 256 of the
    training windows). ``init``: a checkpoint to fine-tune (its architecture replaces
    ``config.train.model``; ``config.train.steps`` more optimizer steps are taken from its weights
    and optimizer state). Returns (model in eval mode, threshold, training record)."""
    in_train = np.isin(data.trial, train_trials)
    rows = np.flatnonzero(in_train & data.labelled)
    train_rows = balanced_rows(rows, data.labels[rows])
    if monitor is None:
        monitor = np.random.default_rng(config.train.seed).permutation(rows)[:MONITOR_WINDOWS]
    result = train(fit_train_config(config, init), Split(data.windows, train_rows, monitor, "object"), resume=init)
    width = data.windows.sequences.frame_width_px
    probability = predict_rows(partial(predict_proba, result.model, width_px=width), data.windows,
                               np.flatnonzero(in_train))
    scores = trial_scores(probability, data.trial[in_train], len(data.objects), config.rule.top_k)
    threshold = choose_threshold(scores[train_trials], data.trial_labels[train_trials])
    record = {"train_windows": int(rows.size), "steps": result.step, "windows_per_s": result.windows_per_s,
              "monitor": result.history[-1] if result.history else None, "threshold": threshold}
    return result.model, threshold, record


def judge(model: nn.Module, data: TrialWindows, trials: np.ndarray, threshold: float, top_k: int) -> dict[str, object]:
    """Window- and trial-level metrics of ``model`` on ``trials`` (trial indices): window_accuracy
    (labelled windows, p >= 0.5; None when the rule labels none of them, as in a slip trial too short
    for its slip windows: that ended in an error), trial_accuracy, confusion (trial level, [[TN, FP],
    [FN, TP]]), n_trials, n_windows (labelled), and per-trial scores."""
    rows = np.flatnonzero(np.isin(data.trial, trials))
    probability = predict_rows(partial(predict_proba, model, width_px=data.windows.sequences.frame_width_px),
                               data.windows, rows)
    labelled = data.labelled[rows]
    window = (classification_metrics(data.labels[rows][labelled], (probability[labelled] >= 0.5).astype(np.int64))
              if labelled.any() else None)
    scores = trial_scores(probability, data.trial[rows], len(data.objects), top_k)[trials]
    trial = classification_metrics(data.trial_labels[trials], (scores >= threshold).astype(np.int64))
    return {"window_accuracy": window.accuracy if window else None, "n_windows": window.n if window else 0,
            "trial_accuracy": trial.accuracy,
            "trial_f1": trial.f1, "confusion": [list(r) for r in trial.confusion], "n_trials": trial.n,
            "threshold": threshold, "scores": scores.tolist()}


def fold_summary(rows: Sequence[dict[str, object]]) -> dict[str, object]:
    """Trial accuracy over cross-validation folds (``rows``, each with fold, trial_accuracy and a
    trial confusion [[TN, FP], [FN, TP]]): mean, std, min, worst fold, pooled accuracy and confusion."""
    accuracy = [r["trial_accuracy"] for r in rows]
    worst = min(rows, key=lambda r: r["trial_accuracy"])
    confusion = np.sum([r["confusion"] for r in rows], axis=0)
    return {"trial_accuracy_mean": statistics.fmean(accuracy), "trial_accuracy_std": statistics.pstdev(accuracy),
            "trial_accuracy_min": min(accuracy), "worst_fold": worst["fold"],
            "pooled_trial_accuracy": float(np.trace(confusion) / confusion.sum()),
            "pooled_confusion": confusion.tolist()}


_fold: Callable[[object], object] | None = None  # a map_folds worker process's fold function


def _start_worker(fold: Callable) -> None:
    """Process-pool initializer of :func:`map_folds`: the `fv` process's malloc settings (a spawned
    process starts without them), one torch thread, and the fold function (with its data), sent
    once per process."""
    global _fold
    steady_malloc()
    torch.set_num_threads(1)
    _fold = fold


def _run_fold(item: object) -> object:
    return _fold(item)


def map_folds(fold: Callable[[Item], Result], items: Sequence[Item], workers: int = 1,
              progress: bool = False) -> list[Result]:
    """``[fold(item) for item in items]``, in this process (``workers`` 1) or in ``workers``
    spawned processes of one torch thread each (``fold`` must be picklable: a module-level
    function or a functools.partial of one); the results are in the order of ``items``, with a
    progress bar over them when ``progress``. ValueError when ``workers`` < 1."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if workers == 1:
        return [fold(item) for item in tqdm(items, desc="folds", disable=not progress)]
    with ProcessPoolExecutor(min(workers, len(items)), mp_context=multiprocessing.get_context("spawn"),
                             initializer=_start_worker, initargs=(fold,)) as pool:
        return list(tqdm(pool.map(_run_fold, items), total=len(items), desc="folds", disable=not progress))


def _window_fold(data: TrialWindows, config: FitConfig, seed: int, init: str | None,
                 fold: tuple[int, list[str]]) -> dict[str, object]:
    """One fold (index k, its test objects) of :func:`cross_validate`: train on the other objects'
    trials (training seed + k) and judge the test trials."""
    k, group = fold
    held_out = np.isin(np.asarray(data.objects), group)
    test, train_trials = np.flatnonzero(held_out), np.flatnonzero(~held_out)
    monitor = np.random.default_rng(seed).permutation(np.flatnonzero(np.isin(data.trial, test)))[:MONITOR_WINDOWS]
    fold_config = replace(config, train=replace(config.train, seed=config.train.seed + k))
    model, threshold, record = fit(data, train_trials, fold_config, monitor, init)
    metrics = judge(model, data, test, threshold, config.rule.top_k)
    return {"fold": k, "objects": group, "trials": test.tolist(), **metrics, "training": record}


def cross_validate(data: TrialWindows, config: FitConfig, folds: int, seed: int = 0,
                   init: str | None = None, progress: bool = True, workers: int = 1) -> dict[str, object]:
    """Object-held-out cross-validation, the folds in ``workers`` processes (:func:`map_folds`; the
    same figures either way). Returns {"folds": [per fold: test objects, test trial indices and
    their scores, n_trials, window_accuracy, trial_accuracy, confusion, threshold, training
    record], "summary": mean, std, min of window and trial accuracy, worst fold, pooled trial
    confusion}. ``init``: fine-tune every fold from this checkpoint."""
    groups = object_folds(data.objects, folds, seed)
    rows = map_folds(partial(_window_fold, data, config, seed, init), list(enumerate(groups)), workers, progress)
    window_acc = [r["window_accuracy"] for r in rows if r["window_accuracy"] is not None]  # (a fold may label none)
    return {
        "folds": rows,
        "summary": {
            **fold_summary(rows), "window_accuracy_mean": statistics.fmean(window_acc) if window_acc else None,
            "window_accuracy_std": statistics.pstdev(window_acc) if window_acc else None,
            "window_accuracy_min": min(window_acc, default=None),
        },
        "config": {**fit_record(config, init), "folds": folds, "seed": seed},
    }


def fit_record(config: FitConfig, init: str | None) -> dict[str, object]:
    """How a fit's networks are trained, as a cross-validation report records it: {"train": ``config.train`` with
    the architecture that ``init`` (a checkpoint to fine-tune, None: none) gives, "init", "rule"}."""
    return {"train": {**config.train.to_dict(), "model": asdict(fit_train_config(config, init).model)},
            "init": init, "rule": asdict(config.rule)}


def fit_config(arch: str = "convlstm", hidden: int = 16, steps: int = 300, batch_size: int = 32, lr: float = 1e-3,
               seed: int = 0, rule: TrialRule = TrialRule(), progress: bool = False) -> FitConfig:
    """A :class:`FitConfig` for the node's window (10) and grid (30) on one CPU thread."""
    model = ModelConfig(arch=arch, hidden=hidden, field_width_px=FIELD_WIDTH_PX)
    return FitConfig(TrainConfig(model=model, steps=steps, batch_size=batch_size, lr=lr, seed=seed,
                                 eval_every=steps, threads=1, progress=progress), rule)
