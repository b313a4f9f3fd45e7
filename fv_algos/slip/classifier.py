"""Slip inference for the slip_detector node, and the checkpoint file format.

A checkpoint is a ``torch.save`` dict loadable with ``weights_only=True`` holding: format name and
version, the software version that wrote it, the :class:`ModelConfig` (architecture and the fixed
input scale), the model weights, the training step, the optimizer state, the training config and
the metric history.
"""
from __future__ import annotations

import importlib.metadata
import pickle
import time
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from fv_algos.slip.models import (
    N_CHANNELS,
    ModelConfig,
    autocast_context,
    autocast_dtype,
    build_model,
    fast_layout,
    to_model_input,
    usable_device,
    width_gain,
)

CHECKPOINT_FORMAT = "fv-slip-checkpoint"
CHECKPOINT_VERSION = 1


def software_version() -> str:
    """Installed version of the ``fingervision`` package ("unknown" when run from an uninstalled tree)."""
    try:
        return importlib.metadata.version("fingervision")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


@dataclass
class Checkpoint:
    """Contents of a checkpoint file.

    model_state: state_dict of the model built from ``model_config``.
    step: optimizer steps taken so far.
    optimizer_state: Adam state_dict (None for an inference-only export).
    train_config: the TrainConfig as a plain dict (empty when unknown).
    history: metric records, one dict per evaluation (see fv_algos.slip.train).
    """

    model_config: ModelConfig
    model_state: dict[str, torch.Tensor]
    step: int = 0
    optimizer_state: dict[str, object] | None = None
    train_config: dict[str, object] = field(default_factory=dict)
    history: list[dict[str, float]] = field(default_factory=list)
    software_version: str = field(default_factory=software_version)


def save_checkpoint(path: str | Path, checkpoint: Checkpoint) -> Path:
    """Write ``checkpoint`` atomically (temp file then rename); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "format_version": CHECKPOINT_VERSION,
        "software_version": checkpoint.software_version,
        "torch_version": str(torch.__version__),
        "model_config": checkpoint.model_config.to_dict(),
        "model_state": {k: v.detach().cpu().contiguous() for k, v in checkpoint.model_state.items()},
        "step": int(checkpoint.step),
        "optimizer_state": checkpoint.optimizer_state,
        "train_config": checkpoint.train_config,
        "history": checkpoint.history,
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)
    return path


def read_torch_file(path: Path) -> object:
    """What ``torch.save`` wrote to the file ``path``, read with ``weights_only=True`` (tensors and
    plain values only). ValueError naming ``path`` for any file torch cannot read so: text, another
    format, a truncated save, a pickle of other Python objects."""
    try:
        with warnings.catch_warnings():  # torch warns of a pickle protocol it may not read, then says why not
            warnings.filterwarnings("ignore", "Detected pickle protocol", UserWarning)
            return torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, zipfile.BadZipFile, RuntimeError, EOFError, OSError, KeyError, ValueError,
            TypeError, IndexError) as exc:  # IndexError: a text file starting with "t" (a labels.csv)
        text = str(exc)
        if "WeightsUnpickler error:" in text:  # keep torch's reason, not its advice on weights_only=False
            text = text.split("WeightsUnpickler error:", 1)[1].strip().split("\n\n", 1)[0]
        text = text.split(". ", 1)[0]  # its first sentence
        raise ValueError(f"{path} is not a model file that torch.load reads with weights_only=True "
                         f"({type(exc).__name__}: {text or 'the file ends early'})") from exc


def load_checkpoint(path: str | Path, expected: ModelConfig | None = None) -> Checkpoint:
    """Read and validate a checkpoint.

    Raises FileNotFoundError for a missing file, ValueError for a file that is not a slip
    checkpoint, has an unsupported version, or whose model config differs from ``expected``
    (the message lists each differing field).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    payload = read_torch_file(path)
    if isinstance(payload, dict) and "kind" in payload and "format" not in payload:
        raise ValueError(f"{path} holds a {payload['kind']!r} model, which decides once per grasp from whole "
                         "trials (fv eval --trials), not a classifier of windows of fields")
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a slip checkpoint (no {CHECKPOINT_FORMAT!r} format tag)")
    if payload.get("format_version") != CHECKPOINT_VERSION:
        raise ValueError(
            f"{path}: checkpoint format version {payload.get('format_version')!r} is not supported "
            f"(expected {CHECKPOINT_VERSION})"
        )
    config = ModelConfig.from_dict(payload["model_config"])
    if expected is not None and config != expected:
        raise ValueError(f"{path}: checkpoint model config does not match: {'; '.join(config.mismatches(expected))} (checkpoint != expected)")
    return Checkpoint(
        model_config=config,
        model_state=payload["model_state"],
        step=int(payload["step"]),
        optimizer_state=payload.get("optimizer_state"),
        train_config=dict(payload.get("train_config", {})),
        history=list(payload.get("history", [])),
        software_version=str(payload.get("software_version", "unknown")),
    )


def model_from_checkpoint(checkpoint: Checkpoint) -> nn.Module:
    """The model described by ``checkpoint`` with its weights loaded, in eval mode."""
    model = build_model(checkpoint.model_config)
    try:
        model.load_state_dict(checkpoint.model_state)
    except RuntimeError as exc:
        raise ValueError(f"checkpoint weights do not fit {checkpoint.model_config}: {exc}") from exc
    return model.eval()


def validate_windows(windows: np.ndarray, config: ModelConfig) -> np.ndarray:
    """Check a batch (B, T, H, W, 3) of windows against ``config``; returns it as float32.

    Raises ValueError for a wrong shape or any NaN/inf value (naming how many). Finite values of
    any size are accepted: the model clamps its scaled input.
    """
    arr = np.asarray(windows)
    expected = (config.window, config.grid, config.grid, 3)
    if arr.ndim != 5 or tuple(arr.shape[1:]) != expected:
        raise ValueError(f"windows must have shape (B, {', '.join(map(str, expected))}), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(f"windows must be floating point (px), got dtype {arr.dtype}")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise ValueError(f"windows contain {int(bad.sum())} non-finite values (NaN/inf); cannot classify")
    return np.clip(arr, -np.finfo(np.float32).max, np.finfo(np.float32).max).astype(np.float32)


def predict_proba(
    model: nn.Module,
    windows: np.ndarray,
    autocast: torch.dtype | None = None,
    device: str | torch.device = "cpu",
    width_px: int | None = None,
) -> np.ndarray:
    """Slip probabilities (B,) float64 in [0, 1] for windows (B, T, H, W, 3) px of frames
    ``width_px`` wide (rescaled by :func:`fv_algos.slip.models.width_gain`; None: taken as they come).

    ``model`` must carry a ``config`` (:class:`ModelConfig`); ``autocast`` runs the forward pass
    under ``torch.autocast`` with that dtype (e.g. torch.bfloat16). The softmax is taken in
    float32. Raises ValueError for invalid input and if the model yields non-finite logits. No windows
    (B = 0) give no probabilities (the CNN+LSTM's reshape raised RuntimeError).
    """
    x = to_model_input(validate_windows(windows, model.config), width_gain(model.config, width_px)).to(device)
    if x.shape[0] == 0:
        return np.zeros(0, np.float64)
    with torch.inference_mode():
        with autocast_context(device, autocast):
            logits = model(x).float()
        if not torch.isfinite(logits).all():
            raise ValueError("model produced non-finite logits; refusing to report a probability")
        prob = torch.softmax(logits, dim=1)[:, 1]
    return prob.clamp(0.0, 1.0).cpu().numpy().astype(np.float64)


class SlipClassifier:
    """Slip probability of one window at a time, for the slip_detector node.

    source: a checkpoint path or a model built by :func:`fv_algos.slip.models.build_model`.
    expected: if given, the checkpoint's model config must equal it.
    threads: torch intra-op threads to use (None leaves torch's setting alone).
    precision: "auto" (bf16 autocast on a CPU with native bf16 hardware, about 2x faster than
        fp32 there, else fp32), "fp32" or "bf16" (see :func:`fv_algos.slip.models.autocast_dtype`).
    """

    def __init__(
        self,
        source: str | Path | nn.Module,
        expected: ModelConfig | None = None,
        device: str = "cpu",
        threads: int | None = None,
        precision: str = "auto",
    ) -> None:
        if isinstance(source, nn.Module):
            if not isinstance(getattr(source, "config", None), ModelConfig):
                raise ValueError("model has no ModelConfig `config` attribute; build it with build_model()")
            if expected is not None and source.config != expected:
                raise ValueError(f"model config does not match: {'; '.join(source.config.mismatches(expected))}")
            model = source.eval()
        else:
            model = model_from_checkpoint(load_checkpoint(source, expected))
        if threads is not None:
            torch.set_num_threads(threads)
        self.device = usable_device(device)
        self.autocast = autocast_dtype(precision, self.device)
        self.model = fast_layout(model.to(self.device), self.autocast)

    @property
    def config(self) -> ModelConfig:
        """The model's configuration (window length, grid, input scale...)."""
        return self.model.config

    def warm_up(self) -> float:
        """One forward pass on a window of zeros, so that the first real window does not pay for the
        backend's one-time set-up: without it, the pipeline's first decision on an H200 (`device:=cuda`,
        the paper's ConvLSTM) came 0.36 s after its frame, the next ones 9 to 12 ms; with it, 10.6 ms
        (this pass took 0.81 s at start-up). Returns that pass's wall time in s."""
        cfg = self.config
        started = time.perf_counter()
        self.predict(np.zeros((cfg.window, cfg.grid, cfg.grid, N_CHANNELS), np.float32))
        return time.perf_counter() - started

    def predict(self, window: np.ndarray, width_px: int | None = None) -> float:
        """Slip probability in [0, 1] for one window (T, H, W, 3) float px of frames ``width_px``
        wide (None: taken as they come; see :func:`fv_algos.slip.models.width_gain`); ValueError on NaN/inf."""
        arr = np.asarray(window)
        if arr.ndim != 4:
            raise ValueError(f"window must have shape (T, H, W, 3), got {arr.shape}")
        return float(predict_proba(self.model, arr[None], self.autocast, self.device, width_px)[0])
