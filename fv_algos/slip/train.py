"""Training loop for the slip classifiers: cross-entropy, Adam, checkpoints, resume, DDP.

Single process: ``train(TrainConfig(...), split)``. Data-parallel: launch
``python -m torch.distributed.run --nproc_per_node N -m fv_algos.slip.train --data D.npz --out DIR``;
each rank computes 1/N of every global batch (``batch_size`` is the global batch), gradients are
averaged by DistributedDataParallel (gloo on CPU, nccl on CUDA), and only rank 0 evaluates and
writes the checkpoint and metrics.

Optimisation: Adam with a linear warm-up over ``warmup_steps`` then a cosine decay of the learning
rate to ``min_lr_fraction * lr`` at ``steps`` (a pure function of the step, see :func:`lr_at`),
gradient-norm clipping, and on CPUs with native bf16 hardware (AVX512-BF16/AMX) the forward and
backward passes run under ``torch.autocast(bfloat16)`` with channels-last activations while the
master weights and Adam state stay float32 (``precision="auto"``).

Batches are a pure function of (seed, step): step s of epoch e = s // (N_train // batch_size)
takes its slice of a permutation drawn from ``numpy.random.default_rng([seed, e])``, so a run
resumed from a checkpoint sees exactly the batches the uninterrupted run would have.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.nn import functional as F
from tqdm import tqdm

from fv_algos.allocator import steady_malloc
from fv_algos.slip.classifier import Checkpoint, load_checkpoint, save_checkpoint
from fv_algos.slip.models import (
    ARCHS,
    PRECISIONS,
    ModelConfig,
    autocast_context,
    autocast_dtype,
    build_model,
    fast_layout,
    to_model_input,
    usable_device,
    width_gain,
)
from fv_algos.slip.windows import SPLIT_KINDS, SequenceSet, Split, load_sequences, make_windows, split_windows, with_extra_training

PAPER_LR = 1e-5
MAX_LR = float(np.finfo(np.float32).max) / 10  # Adam's first step is 10 lr (its bias correction), in float32
SCHEDULES = ("cosine", "constant")
CHECKPOINT_NAME = "checkpoint.pt"
METRICS_NAME = "metrics.json"


@dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters.

    lr: peak Adam learning rate; the default 1e-3 is tuned on the simulated fields (the paper's is
        PAPER_LR = 1e-5, which needs many more steps).
    schedule: "cosine" (warm-up, then cosine decay to min_lr_fraction * lr at ``steps``) or
        "constant" (warm-up, then lr).
    warmup_steps: steps of linear learning-rate warm-up from lr / warmup_steps to lr.
    min_lr_fraction: final learning rate of the cosine schedule, as a fraction of lr.
    grad_clip: clip the global gradient L2 norm to this (None: no clipping).
    precision: "auto" (bf16 autocast on a CPU with native bf16 hardware, else fp32), "fp32" or
        "bf16"; weights and optimizer state are float32 in every case.
    batch_size: global batch (windows per optimizer step), split evenly over DDP ranks.
    eval_every: steps between evaluations (metrics record + checkpoint).
    eval_windows: test windows scored at intermediate evaluations (a fixed seeded subset);
        the final evaluation scores the whole test set.
    out_dir: where checkpoint.pt and metrics.json go (None: nothing is written).
    threads: torch intra-op threads (None leaves torch's setting alone).
    """

    model: ModelConfig = field(default_factory=ModelConfig)
    steps: int = 600
    batch_size: int = 32
    lr: float = 1e-3
    schedule: str = "cosine"
    warmup_steps: int = 20
    min_lr_fraction: float = 0.02
    grad_clip: float | None = 1.0
    precision: str = "auto"
    seed: int = 0
    eval_every: int = 50
    eval_windows: int = 256
    out_dir: str | None = None
    device: str = "cpu"
    threads: int | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "eval_every", "eval_windows"):
            if getattr(self, name) < 1:
                raise ValueError(f"TrainConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not 0 < self.lr < MAX_LR:  # (NaN fails both)
            raise ValueError(f"TrainConfig.lr must be > 0 and below {MAX_LR:.3g} (Adam's first step, 10 lr, is a "
                             f"float32), got {self.lr}")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"TrainConfig.schedule must be one of {SCHEDULES}, got {self.schedule!r}")
        if self.warmup_steps < 0:
            raise ValueError(f"TrainConfig.warmup_steps must be >= 0, got {self.warmup_steps}")
        if not 0.0 <= self.min_lr_fraction <= 1.0:
            raise ValueError(f"TrainConfig.min_lr_fraction must be in [0, 1], got {self.min_lr_fraction}")
        if self.grad_clip is not None and not (np.isfinite(self.grad_clip) and self.grad_clip > 0):
            raise ValueError(f"TrainConfig.grad_clip must be finite and > 0 (or None), got {self.grad_clip}")
        if not 0 <= self.seed < 2**63:
            raise ValueError(f"TrainConfig.seed must be from 0 to 2**63 - 1, got {self.seed}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"TrainConfig.precision must be one of {PRECISIONS}, got {self.precision!r}")

    def to_dict(self) -> dict[str, object]:
        """Plain nested dict (the model config included), for checkpoints and JSON."""
        return asdict(self)


@dataclass
class TrainResult:
    """Outcome of :func:`train`.

    model: the trained model (unwrapped from DDP), in eval mode, on the training device.
    history: one record per evaluation: step, train_loss, train_accuracy (averaged over the
        steps since the previous record; under DDP over rank 0's share of each batch), test_loss,
        test_accuracy, test_windows, elapsed_s.
    windows_per_s: training throughput (global windows per second of optimizer steps, excluding
        evaluation), over the steps run in this call.
    windows_per_cpu_s: the same per second of this process's CPU time divided by its torch
        threads: close to windows_per_s on a quiet machine, and an estimate of it when other
        processes compete for the cores; None when training on another device than the CPU.
    autocast: the autocast dtype used ("bfloat16") or None for plain fp32.
    param_digest: SHA-256 of the final parameters (equal on every DDP rank when in sync).
    checkpoint_path: the last checkpoint written (None when out_dir is None or not rank 0).
    """

    model: nn.Module
    history: list[dict[str, float]]
    step: int
    windows_per_s: float
    param_digest: str
    checkpoint_path: Path | None
    windows_per_cpu_s: float | None = 0.0
    autocast: str | None = None


def lr_at(config: TrainConfig, step: int) -> float:
    """Learning rate of optimizer step ``step`` (0-based) under ``config``'s schedule."""
    if step < config.warmup_steps:
        return config.lr * (step + 1) / config.warmup_steps
    if config.schedule == "constant":
        return config.lr
    span = max(1, config.steps - config.warmup_steps)
    progress = min(1.0, (step - config.warmup_steps) / span)
    floor = config.min_lr_fraction
    return float(config.lr * (floor + (1.0 - floor) * 0.5 * (1.0 + np.cos(np.pi * progress))))


def batch_rows(train_rows: np.ndarray, batch_size: int, seed: int, step: int) -> np.ndarray:
    """Window rows (batch_size,) int64 of optimizer step ``step`` (epoch-wise shuffling, drop last)."""
    n = train_rows.size
    if n < batch_size:
        raise ValueError(f"training split has {n} windows, fewer than batch_size={batch_size}")
    per_epoch = n // batch_size
    epoch, k = divmod(step, per_epoch)
    order = np.random.default_rng([seed, epoch]).permutation(n)
    return train_rows[order[k * batch_size : (k + 1) * batch_size]]


def parameter_digest(model: nn.Module) -> str:
    """SHA-256 hex digest of all parameters' bytes (in state_dict order)."""
    digest = hashlib.sha256()
    for tensor in model.state_dict().values():
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def data_gain(config: ModelConfig, data: Split) -> float:
    """:func:`width_gain` of ``data``'s fields (their sequences' ``frame_width_px``) for ``config``."""
    return width_gain(config, data.windows.sequences.frame_width_px)


def _score(model: nn.Module, data: Split, rows: np.ndarray, device: torch.device, amp: torch.dtype | None,
           batch: int = 128) -> tuple[float, float]:
    """Mean cross-entropy and accuracy of ``model`` on window rows (forward under autocast ``amp``); a window
    whose logits are not finite counts as wrong (argmax would call it class 0)."""
    gain = data_gain(model.config, data)
    model.eval()
    loss_sum, correct = 0.0, 0
    with torch.inference_mode():
        for lo in range(0, rows.size, batch):
            x, y = data.windows.get(rows[lo : lo + batch])
            with autocast_context(device, amp):
                logits = model(to_model_input(x, gain).to(device)).float()
            target = torch.as_tensor(y, device=device)
            loss_sum += float(F.cross_entropy(logits, target, reduction="sum"))
            correct += int(((logits.argmax(1) == target) & torch.isfinite(logits).all(1)).sum())  # NaN: wrong
    model.train()
    return loss_sum / rows.size, correct / rows.size


def train(config: TrainConfig, data: Split, resume: str | Path | None = None) -> TrainResult:
    """Train ``config.model`` on ``data.train`` until ``config.steps`` optimizer steps, scoring on
    ``data.test``. ``resume``: a checkpoint to continue from (its model config must equal
    ``config.model``, else ValueError naming the differing fields). Works inside a
    ``torch.distributed`` process group (DDP) when one is initialised."""
    if config.threads is not None:
        torch.set_num_threads(config.threads)
    distributed = dist.is_available() and dist.is_initialized()
    rank, world = (dist.get_rank(), dist.get_world_size()) if distributed else (0, 1)
    if config.batch_size % world:
        raise ValueError(f"batch_size={config.batch_size} is not divisible by the {world} DDP ranks")
    if data.windows.window != config.model.window or data.windows.sequences.grid != config.model.grid:
        raise ValueError(
            f"data windows are {data.windows.window} frames on a {data.windows.sequences.grid} grid, "
            f"model expects {config.model.window} frames on a {config.model.grid} grid"
        )
    device = usable_device(config.device)
    amp = autocast_dtype(config.precision, device)
    torch.manual_seed(config.seed)
    model = fast_layout(build_model(config.model).to(device), amp)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    step, history, gain = 0, [], data_gain(config.model, data)
    if resume is not None:
        checkpoint = load_checkpoint(resume, expected=config.model)
        model.load_state_dict(checkpoint.model_state)
        if checkpoint.optimizer_state is not None:
            optimizer.load_state_dict(checkpoint.optimizer_state)
        step, history = checkpoint.step, list(checkpoint.history)
        if step >= config.steps:  # nothing would be trained, and no checkpoint written in out_dir
            raise ValueError(f"--resume {resume} is at step {step} already: ask for more --steps than that "
                             f"(got {config.steps})")
    net: nn.Module = nn.parallel.DistributedDataParallel(model) if distributed else model
    eval_rows = np.random.default_rng(config.seed).permutation(data.test)[: config.eval_windows]
    out_dir = Path(config.out_dir) if config.out_dir is not None and rank == 0 else None
    checkpoint_path = None
    loss_sum, correct, seen, train_time, train_cpu, start_step = 0.0, 0, 0, 0.0, 0.0, step
    threads = torch.get_num_threads()
    started = time.perf_counter()
    net.train()
    bar = tqdm(total=config.steps, initial=step, disable=not config.progress or rank != 0, desc="train", unit="step")
    while step < config.steps:
        t0, c0 = time.perf_counter(), time.process_time()
        rows = batch_rows(data.train, config.batch_size, config.seed, step)[rank::world]
        x, y = data.windows.get(rows)
        target = torch.as_tensor(y, device=device)
        with autocast_context(device, amp):
            logits = net(to_model_input(x, gain).to(device)).float()
        loss = F.cross_entropy(logits, target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if config.grad_clip is not None:
            nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
        for group in optimizer.param_groups:
            group["lr"] = lr_at(config, step)
        optimizer.step()
        step += 1
        finite = torch.stack([torch.isfinite(p).all() for p in model.parameters()]).all()  # one sync per step
        loss_value = float(loss.detach())
        if not finite:  # the same on every DDP rank: the parameters are
            kept = f"; {checkpoint_path} keeps step {history[-1]['step']}" if checkpoint_path is not None else ""
            raise ValueError(f"training diverged at step {step}: loss {loss_value:.3g} and parameters "
                             f"no longer finite (lr {config.lr:g}: try a lower one, or grad_clip){kept}")
        train_time += time.perf_counter() - t0
        train_cpu += (time.process_time() - c0) / threads
        loss_sum += loss_value * rows.size
        correct += int((logits.argmax(1) == target).sum())
        seen += rows.size
        bar.update(1)
        last = step == config.steps
        if rank == 0 and (step % config.eval_every == 0 or last):
            test_loss, test_acc = _score(model, data, data.test if last else eval_rows, device, amp)
            record = {
                "step": step,
                "train_loss": loss_sum / seen,
                "train_accuracy": correct / seen,
                "test_loss": test_loss,
                "test_accuracy": test_acc,
                "test_windows": int(data.test.size if last else eval_rows.size),
                "elapsed_s": time.perf_counter() - started,
                "lr": lr_at(config, step - 1),
            }
            history.append(record)
            bar.set_postfix(loss=f"{record['train_loss']:.3f}", test_acc=f"{test_acc:.3f}")
            loss_sum, correct, seen = 0.0, 0, 0
            if out_dir is not None:
                checkpoint_path = save_checkpoint(
                    out_dir / CHECKPOINT_NAME,
                    Checkpoint(config.model, model.state_dict(), step, optimizer.state_dict(), config.to_dict(), history),
                )
                _write_json(out_dir / METRICS_NAME, {"train_config": config.to_dict(), "history": history})
    bar.close()
    steps_run = step - start_step
    windows_per_s = steps_run * config.batch_size / train_time if train_time > 0 else 0.0
    windows_per_cpu_s = steps_run * config.batch_size / train_cpu if train_cpu > 0 else 0.0
    if device.type != "cpu":  # the steps wait on the device: CPU time says nothing of their speed
        windows_per_cpu_s = None
    model = model.to(memory_format=torch.contiguous_format).eval()
    return TrainResult(model, history, step, windows_per_s, parameter_digest(model), checkpoint_path,
                       windows_per_cpu_s, None if amp is None else str(amp).removeprefix("torch."))


def _write_json(path: Path, payload: dict[str, object]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(payload, indent=1))
    tmp.replace(path)


def _parse(argv: list[str] | None) -> argparse.Namespace:
    defaults_m, defaults_t = ModelConfig(), TrainConfig()
    p = argparse.ArgumentParser(prog="python -m fv_algos.slip.train", description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="sequence dataset .npz (fv_algos.slip.windows.save_sequences)")
    p.add_argument("--extra", default=None, help="a second sequence dataset whose windows only add to the training "
                   "rows (e.g. whole grasps, `fv dataset sim --grasps`); the test rows stay --data's")
    p.add_argument("--out", required=True, help="output folder for checkpoint.pt, metrics.json, result_rank<r>.json")
    p.add_argument("--resume", default=None, help="checkpoint to continue from")
    p.add_argument("--split", choices=SPLIT_KINDS, default="sequence",
                   help="default sequence, as `fv train` (random is the paper's split: windows of one sequence "
                        "on both sides)")
    p.add_argument("--test-fraction", type=float, default=0.1)
    p.add_argument("--per-sequence", type=int, default=5, help="windows kept per raw sequence")
    p.add_argument("--arch", choices=ARCHS, default=defaults_m.arch)
    p.add_argument("--hidden", type=int, default=defaults_m.hidden)
    p.add_argument("--kernel", type=int, default=defaults_m.kernel)
    p.add_argument("--window", type=int, default=defaults_m.window)
    p.add_argument("--scale-px", type=float, default=defaults_m.scale_px)
    p.add_argument("--steps", type=int, default=defaults_t.steps)
    p.add_argument("--batch-size", type=int, default=defaults_t.batch_size)
    p.add_argument("--lr", type=float, default=defaults_t.lr)
    p.add_argument("--schedule", choices=SCHEDULES, default=defaults_t.schedule)
    p.add_argument("--warmup-steps", type=int, default=defaults_t.warmup_steps)
    p.add_argument("--precision", choices=PRECISIONS, default=defaults_t.precision)
    p.add_argument("--seed", type=int, default=defaults_t.seed)
    p.add_argument("--eval-every", type=int, default=defaults_t.eval_every)
    p.add_argument("--eval-windows", type=int, default=defaults_t.eval_windows)
    p.add_argument("--device", default=defaults_t.device)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def main(argv: list[str] | None = None, sequences: SequenceSet | None = None,
         extra: SequenceSet | None = None) -> int:
    """Command-line entry (also what torchrun runs); writes result_rank<r>.json with the
    parameter digest and final metrics for every rank. Returns the exit status. ``sequences`` and
    ``extra``: the files of --data and --extra when the caller has read them already (`fv train`)."""
    steady_malloc()  # this is the process entry under torchrun
    args = _parse(argv)
    sequences = load_sequences(args.data) if sequences is None else sequences
    model_config = ModelConfig(
        arch=args.arch, hidden=args.hidden, kernel=args.kernel, window=args.window,
        grid=sequences.grid, scale_px=args.scale_px, field_width_px=sequences.frame_width_px,
    )
    config = TrainConfig(
        model=model_config, steps=args.steps, batch_size=args.batch_size, lr=args.lr, schedule=args.schedule,
        warmup_steps=args.warmup_steps, precision=args.precision, seed=args.seed,
        eval_every=args.eval_every, eval_windows=args.eval_windows, out_dir=args.out, device=args.device,
        threads=args.threads, progress=not args.no_progress,
    )
    windows = make_windows(sequences, window=args.window, per_sequence=args.per_sequence)
    split = split_windows(windows, args.split, args.test_fraction, args.seed)
    if args.extra is not None:
        split = with_extra_training(split, load_sequences(args.extra) if extra is None else extra)
    launched = int(os.environ.get("WORLD_SIZE", "1")) > 1
    if launched:
        cuda = torch.device(args.device).type == "cuda"
        dist.init_process_group("nccl" if cuda else "gloo")
        if cuda:
            config = replace(config, device=f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}")
    try:
        result = train(config, split, resume=args.resume)
        rank = dist.get_rank() if launched else 0
        _write_json(
            Path(args.out) / f"result_rank{rank}.json",
            {"step": result.step, "param_digest": result.param_digest, "windows_per_s": result.windows_per_s,
             "windows_per_cpu_s": result.windows_per_cpu_s, "autocast": result.autocast,
             "final": result.history[-1] if result.history else None},
        )
        if launched:  # the other ranks wait for rank 0's last evaluation: no rank tears its process group
            dist.barrier()  # down while another still holds its connections (a rank once aborted there)
    finally:
        if launched:
            dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
