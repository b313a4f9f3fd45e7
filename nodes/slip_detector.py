"""The `slip_detector` node: DisplacementField -> SlipState on `/slip` at the field rate.

It keeps the last `window` fields (the model's window length), asks the ConvLSTM for
P(slip), and decides with a threshold and optional hysteresis. Every field enters the
window, but when the model falls behind (newer fields already queued) only the newest
window is judged: the skipped decisions are counted, and latency stays one model call.
`model` is a shipped model name (`sim_cnn_lstm`: per-field CNN then LSTM, the default and
the fastest; `sim_fast`: the ConvLSTM with 16 hidden channels; `sim`: the paper's ConvLSTM;
`gelsight`) or a checkpoint path."""
from __future__ import annotations

import collections
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msgs import DisplacementField, SlipState
from nodes.node import Node

WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "fv_algos" / "weights"


def model_path(name: str) -> Path:
    """Checkpoint path of a shipped model name, or the path itself; FileNotFoundError
    naming the shipped models."""
    shipped = WEIGHTS_DIR / f"slip_{name}.pt"
    if shipped.is_file():
        return shipped
    path = Path(name)
    if path.is_file():
        return path
    names = sorted(p.stem.removeprefix("slip_") for p in WEIGHTS_DIR.glob("slip_*.pt"))
    raise FileNotFoundError(f"model {name!r} is neither a shipped model ({names}) nor a checkpoint file")


@dataclass
class SlipDetectorParams:
    model: str = "sim_cnn_lstm"  # shipped model name (sim_cnn_lstm, sim_fast, sim, gelsight) or checkpoint path
    threshold: float = 0.5  # P(slip) above which the state is slip
    hysteresis: float = 0.0  # slip turns on above threshold + h and off below threshold - h
    threads: int = 1  # torch threads for inference
    device: str = "cpu"  # cpu | cuda
    input_timeout_s: float = 2.0  # warn in NodeStatus after this long without a field (0 = never)

    def __post_init__(self) -> None:
        if not 0.0 < self.threshold < 1.0:
            raise ValueError(f"threshold {self.threshold} must be in (0, 1)")
        if not 0.0 <= self.hysteresis < min(self.threshold, 1.0 - self.threshold):
            raise ValueError(f"hysteresis {self.hysteresis} must be >= 0 and keep threshold +/- h inside (0, 1)")


class SlipDetectorNode(Node):
    """Slides a window over the fields and publishes a decision per field."""

    Params = SlipDetectorParams

    @classmethod
    def preload(cls) -> None:
        import fv_algos.slip.classifier  # noqa: F401  (torch: the bulk of a cold start)

    def setup(self) -> None:
        from fv_algos.slip.classifier import SlipClassifier
        p = self.params
        self.classifier = SlipClassifier(model_path(p.model), device=p.device, threads=p.threads)
        cfg = self.classifier.config
        self.window: collections.deque = collections.deque(maxlen=cfg.window)
        self.slip = False
        self.slip_pub = self.publisher("/slip", SlipState)
        self.field_sub = self.subscribe("/field", DisplacementField, self.on_field, depth=cfg.window,
                                        stale_after_s=p.input_timeout_s or None)
        self.counters.update(decisions=0, invalid_windows=0, skipped=0)
        self.log.info("model %s: window %d, grid %d", p.model, cfg.window, cfg.grid)

    def on_field(self, msg: DisplacementField) -> None:
        grid = self.classifier.config.grid
        if msg.field.shape[:2] != (grid, grid):
            raise ValueError(f"field grid {msg.field.shape[:2]} does not match the model's {grid}x{grid}: "
                             "set the interpolator's grid param")
        self.window.append((msg.stamp_ns, msg.field, msg.valid))
        if len(self.window) < self.window.maxlen:
            return
        if self.field_sub.queue:  # newer fields wait: judge only the newest window (latency stays one call)
            self.counters["skipped"] += 1
            return
        stamps = np.array([s for s, _, _ in self.window], np.int64)
        valid = all(v for _, _, v in self.window)
        probability = 0.0
        if valid:
            try:
                probability = self.classifier.predict(np.stack([f for _, f, _ in self.window]))
            except ValueError as exc:  # non-finite field values: flag the window, keep running
                self.warn(f"window rejected: {exc}")
                valid = False
        if valid:
            p = self.params
            if probability > p.threshold + p.hysteresis:
                self.slip = True
            elif probability < p.threshold - p.hysteresis:
                self.slip = False
        else:
            self.counters["invalid_windows"] += 1
        self.counters["decisions"] += 1
        self.slip_pub.publish(SlipState(stamp_ns=msg.stamp_ns, frame_id=msg.frame_id, probability=probability,
                                        slip=self.slip, threshold=self.params.threshold,
                                        window_stamps_ns=stamps, model=self.params.model, valid=valid))
