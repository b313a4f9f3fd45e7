"""Slip classifiers over windows of displacement fields: the paper's ConvLSTM and two baselines.

Every model takes a batch ``x`` of shape (B, T, 3, H, W) float32 in pixels (channels dx, dy,
magnitude) and returns logits (B, 2) float32 (class 0 = no slip, 1 = slip). Windows are stored
channel-last, (B, T, H, W, 3); :func:`to_model_input` is the one place that transposes them.

Input scaling is fixed per model, not fitted to data: the first operation of every forward pass
divides by ``ModelConfig.scale_px`` and clamps to ``[-clip, clip]`` (see :class:`FieldNormaliser`),
so fields of any size (1e6 px included) stay finite in fp16/bf16, and the scale travels inside
the checkpoint with the rest of the config.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

ARCHS = ("convlstm", "cnn_lstm", "lstm")
PRECISIONS = ("auto", "fp32", "bf16")
N_CLASSES = 2
N_CHANNELS = 3


@dataclass(frozen=True)
class ModelConfig:
    """Architecture and input scaling of a slip classifier.

    arch: "convlstm" (the paper's model), "cnn_lstm" (per-frame CNN then LSTM, after Li et al.)
        or "lstm" (LSTM on the field average-pooled to ``pool`` x ``pool`` cells).
    hidden: hidden channels (ConvLSTM) or hidden units (LSTM).
    kernel: ConvLSTM kernel size, odd; 3 reproduces the paper's 269,826 parameters, 5 is what
        its text says.
    window: frames per window, T.
    grid: displacement-field grid size, H = W.
    scale_px: displacement (px) that maps to 1.0 at the model input.
    clip: bound on the scaled input, |x / scale_px| <= clip.
    pool: cells per side of the pooled field fed to the "lstm" baseline.
    field_width_px: width (px) of the camera frames the training fields were measured in
        (``scale_px`` is in their px); a field from frames of another width is rescaled to it
        first (:func:`width_gain`), since displacements in px scale with
        the frame width. None: fields are taken as they come (fields of no camera, and
        checkpoints from before this setting).
    """

    arch: str = "convlstm"
    hidden: int = 64
    kernel: int = 3
    window: int = 10
    grid: int = 30
    scale_px: float = 5.0
    clip: float = 20.0
    pool: int = 6
    field_width_px: int | None = None

    def __post_init__(self) -> None:
        if self.arch not in ARCHS:
            raise ValueError(f"ModelConfig.arch must be one of {ARCHS}, got {self.arch!r}")
        for name in ("hidden", "window", "grid", "pool"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"ModelConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.kernel < 1 or self.kernel % 2 == 0:
            raise ValueError(f"ModelConfig.kernel must be a positive odd integer, got {self.kernel}")
        if not (np.isfinite(self.scale_px) and self.scale_px > 0):
            raise ValueError(f"ModelConfig.scale_px must be finite and > 0, got {self.scale_px}")
        if not (np.isfinite(self.clip) and self.clip > 0):
            raise ValueError(f"ModelConfig.clip must be finite and > 0, got {self.clip}")
        if self.field_width_px is not None and (isinstance(self.field_width_px, bool)
                                                or not isinstance(self.field_width_px, int) or self.field_width_px < 1):
            raise ValueError(f"ModelConfig.field_width_px must be None or a positive int, got {self.field_width_px!r}")
        if self.arch == "lstm" and self.pool > self.grid:
            raise ValueError(f"ModelConfig.pool ({self.pool}) must not exceed grid ({self.grid})")

    def to_dict(self) -> dict[str, object]:
        """Plain dict of the fields (for checkpoints and JSON)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> ModelConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ValueError naming them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown ModelConfig fields: {unknown}")
        return cls(**data)  # type: ignore[arg-type]

    def mismatches(self, other: ModelConfig) -> list[str]:
        """Human-readable list of fields that differ, e.g. ["hidden: 64 != 32"]."""
        return [
            f"{f.name}: {getattr(self, f.name)!r} != {getattr(other, f.name)!r}"
            for f in fields(self)
            if getattr(self, f.name) != getattr(other, f.name)
        ]


def bf16_fast_on_cpu() -> bool:
    """True when this CPU has native bf16 matrix hardware (AVX512-BF16 or AMX) that oneDNN uses,
    so bf16 convolutions beat fp32 ones; False on CPUs that would only emulate bf16."""
    if not torch.backends.mkldnn.is_available():
        return False
    probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")  # private torch.cpu probes
    return any(bool(getattr(torch.cpu, name)()) for name in probes if hasattr(torch.cpu, name))


def usable_device(name: str | torch.device) -> torch.device:
    """The torch device ``name`` ("cpu", "cuda", "cuda:N", "mps", "xpu", "xpu:N") once it is known to be
    usable in this process: ValueError naming the device and the reason otherwise (torch itself raises
    an AssertionError for a CUDA device in a CPU-only build, and only at the first tensor moved)."""
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"device {str(name)!r} is not a torch device (cpu, cuda, cuda:N, mps, xpu, xpu:N)") from None
    if device.type == "cpu":
        return device
    backend = {"cuda": torch.cuda, "xpu": getattr(torch, "xpu", None), "mps": torch.backends.mps}.get(device.type)
    if backend is None or not backend.is_available():
        raise ValueError(f"device {str(name)!r} is not usable here: this torch ({torch.__version__}) sees no "
                         f"{device.type} device (a CPU-only torch build has none; the README says how GPU users install torch)")
    count = backend.device_count() if hasattr(backend, "device_count") else 1
    if device.index is not None and device.index >= count:
        raise ValueError(f"device {str(name)!r} is not usable here: {count} {device.type} device(s), "
                         f"numbered from 0")
    return device


def autocast_dtype(precision: str, device: str | torch.device = "cpu") -> torch.dtype | None:
    """torch.autocast dtype for a precision name in PRECISIONS: "fp32" -> None (no autocast),
    "bf16" -> torch.bfloat16, "auto" -> torch.bfloat16 on a CPU with native bf16 hardware
    (:func:`bf16_fast_on_cpu`), else None (fp32; also on CUDA)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision == "bf16":
        return torch.bfloat16
    if precision == "auto" and torch.device(device).type == "cpu" and bf16_fast_on_cpu():
        return torch.bfloat16
    return None


def autocast_context(device: str | torch.device, dtype: torch.dtype | None) -> torch.autocast:
    """``torch.autocast`` to ``dtype`` on ``device``'s type; a disabled one when dtype is None (fp32)."""
    return torch.autocast(torch.device(device).type, dtype=dtype or torch.bfloat16, enabled=dtype is not None)


def fast_layout(model: nn.Module, dtype: torch.dtype | None) -> nn.Module:
    """``model`` (changed in place) in the memory layout fastest under autocast ``dtype``:
    channels-last convolution weights for bf16 (oneDNN's bf16 kernels; on an AMX CPU about 1.5x
    faster at batch 1 and 3x in training than channels-first bf16), unchanged otherwise. Weights
    and results are unchanged."""
    if dtype == torch.bfloat16:
        return model.to(memory_format=torch.channels_last)
    return model


def width_gain(config: ModelConfig, width_px: int | None) -> float:
    """Factor that takes fields (px) of frames ``width_px`` wide to px of the frames the model was
    trained on (``config.field_width_px``); 1.0 when either width is unknown (None or 0). ValueError for
    a negative ``width_px`` (its gain would flip the field's sign)."""
    if width_px is not None and width_px < 0:
        raise ValueError(f"width_px must be > 0, or 0 / None when unknown, got {width_px}")
    if not config.field_width_px or not width_px:
        return 1.0
    return config.field_width_px / width_px


def to_model_input(windows: np.ndarray | torch.Tensor, gain: float = 1.0) -> torch.Tensor:
    """(B, T, H, W, 3) channel-last windows (px) -> (B, T, 3, H, W) float32 tensor (px), times ``gain``
    (:func:`width_gain`: px of the frames the model was trained on)."""
    x = torch.as_tensor(windows)
    if x.ndim != 5 or x.shape[-1] != N_CHANNELS:
        raise ValueError(f"windows must have shape (B, T, H, W, 3), got {tuple(x.shape)}")
    x = x.to(torch.float32).permute(0, 1, 4, 2, 3)
    return x if gain == 1.0 else x * gain


class FieldNormaliser(nn.Module):
    """x (px) -> clamp(x / scale_px, -clip, clip); shape-preserving, no parameters."""

    def __init__(self, scale_px: float, clip: float) -> None:
        super().__init__()
        self.inv_scale = 1.0 / scale_px
        self.clip = clip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.clamp(x * self.inv_scale, -self.clip, self.clip)


def _check_input(x: torch.Tensor, config: ModelConfig) -> None:
    expected = (config.window, N_CHANNELS, config.grid, config.grid)
    if x.ndim != 5 or tuple(x.shape[1:]) != expected:
        raise ValueError(f"model input must have shape (B, {', '.join(map(str, expected))}), got {tuple(x.shape)}")


class ConvLSTMClassifier(nn.Module):
    """The paper's model: one ConvLSTM layer, last hidden state -> one linear layer -> 2 logits.

    Gates i, f, o, g come from ONE convolution over concat[x_t, h_{t-1}] (weight
    (4*hidden, 3+hidden, k, k)). The forward pass evaluates that same convolution as
    conv(x_t, W[:, :3]) + conv(h_{t-1}, W[:, 3:]) so the input part runs for all T frames in one
    batched call and the h part is skipped at t=0 (h_0 = 0); the result is identical.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.normalise = FieldNormaliser(config.scale_px, config.clip)
        self.gates = nn.Conv2d(N_CHANNELS + config.hidden, 4 * config.hidden, config.kernel, padding=config.kernel // 2)
        self.head = nn.Linear(config.hidden * config.grid * config.grid, N_CLASSES)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (B, T, 3, H, W) float32 px -> logits (B, 2)."""
        _check_input(x, self.config)
        b, t, _, hgt, wid = x.shape
        hidden, pad = self.config.hidden, self.config.kernel // 2
        x = self.normalise(x).transpose(0, 1).reshape(t * b, N_CHANNELS, hgt, wid)  # time-major
        w_x = self.gates.weight[:, :N_CHANNELS]
        w_h = self.gates.weight[:, N_CHANNELS:]
        gates_x = F.conv2d(x, w_x, self.gates.bias, padding=pad)
        # unbind (not indexing) so autograd stacks the T gradients once instead of scattering
        # each into a zero tensor the size of all T frames
        h = c = None
        for g in gates_x.reshape(t, b, 4 * hidden, hgt, wid).unbind(0):
            if h is not None:
                g = g + F.conv2d(h, w_h, padding=pad)
            ifo = torch.sigmoid(g[:, : 3 * hidden])  # input, forget, output gates in one call
            new = ifo[:, :hidden] * torch.tanh(g[:, 3 * hidden :])
            c = new if c is None else ifo[:, hidden : 2 * hidden] * c + new
            h = ifo[:, 2 * hidden :] * torch.tanh(c)
        assert h is not None
        return self.head(h.flatten(1))


class CnnLstmClassifier(nn.Module):
    """Baseline after Li et al.: a small per-frame CNN (3 -> 16 -> 32 channels, stride 2, then
    adaptive average pool to 4x4 = 512 features), an LSTM over the T feature vectors, and a
    linear layer on the last hidden state."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.normalise = FieldNormaliser(config.scale_px, config.clip)
        self.cnn = nn.Sequential(
            nn.Conv2d(N_CHANNELS, 16, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(4),
            nn.Flatten(),
        )
        self.lstm = nn.LSTM(32 * 4 * 4, config.hidden, batch_first=True)
        self.head = nn.Linear(config.hidden, N_CLASSES)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (B, T, 3, H, W) float32 px -> logits (B, 2)."""
        _check_input(x, self.config)
        b, t = x.shape[:2]
        feats = self.cnn(self.normalise(x).flatten(0, 1)).reshape(b, t, -1)
        out, _ = self.lstm(feats)
        return self.head(out[:, -1])


class PooledLstmClassifier(nn.Module):
    """Baseline: each frame average-pooled to (3, pool, pool), flattened, an LSTM over T, and a
    linear layer on the last hidden state (a summarised-field stand-in for the paper's
    "LSTM on spectral signals" row)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.normalise = FieldNormaliser(config.scale_px, config.clip)
        self.pool = nn.AdaptiveAvgPool2d(config.pool)
        self.lstm = nn.LSTM(N_CHANNELS * config.pool * config.pool, config.hidden, batch_first=True)
        self.head = nn.Linear(config.hidden, N_CLASSES)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (B, T, 3, H, W) float32 px -> logits (B, 2)."""
        _check_input(x, self.config)
        b, t = x.shape[:2]
        feats = self.pool(self.normalise(x).flatten(0, 1)).reshape(b, t, -1)
        out, _ = self.lstm(feats)
        return self.head(out[:, -1])


_BUILDERS: dict[str, type[nn.Module]] = {
    "convlstm": ConvLSTMClassifier,
    "cnn_lstm": CnnLstmClassifier,
    "lstm": PooledLstmClassifier,
}


def build_model(config: ModelConfig) -> nn.Module:
    """A freshly initialised model for ``config`` (uses torch's global RNG for the weights)."""
    return _BUILDERS[config.arch](config)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable scalar parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
