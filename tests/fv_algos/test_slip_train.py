"""Training loop, checkpoints, resume and DDP of fv_algos.slip.train (tiny problems only)."""
from __future__ import annotations

import json
import os
import pickle
import re
from dataclasses import replace
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from fv_algos.slip.classifier import SlipClassifier, load_checkpoint, model_from_checkpoint, save_checkpoint, Checkpoint
from fv_algos.slip.models import ModelConfig, build_model
from fv_algos.trial_net import read_trial_model
from fv_algos.slip.train import TrainConfig, batch_rows, lr_at, main, parameter_digest, train
from fv_algos.slip.windows import (
    SequenceSet,
    Split,
    SyntheticConfig,
    make_windows,
    save_sequences,
    split_windows,
    synthetic_sequences,
    WindowSet,
)

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parents[2]
TINY = ModelConfig(hidden=8, window=4, grid=8)
EASY = SyntheticConfig(grid=8, n_frames=6, slip_speed=(0.5, 1.0), decorrelation=(0.1, 0.2), noise_px=0.05)


@pytest.fixture(scope="module")
def split() -> Split:
    sequences = synthetic_sequences(64, EASY, seed=11)
    return split_windows(make_windows(sequences, window=4, per_sequence=3), "sequence", 0.25, seed=0)


def _config(tmp: Path | None = None, **kw: object) -> TrainConfig:
    base = {"model": TINY, "steps": 6, "batch_size": 8, "lr": 1e-2, "warmup_steps": 2, "eval_every": 3, "progress": False}
    base.update(kw)
    return TrainConfig(out_dir=None if tmp is None else str(tmp), **base)


def test_batch_rows_cover_each_epoch_once_and_are_reproducible() -> None:
    rows = np.arange(100, 120)
    epoch = np.concatenate([batch_rows(rows, 5, seed=1, step=s) for s in range(4)])
    assert sorted(epoch.tolist()) == rows.tolist()
    assert np.array_equal(batch_rows(rows, 5, 1, 2), batch_rows(rows, 5, 1, 2))
    assert not np.array_equal(batch_rows(rows, 5, 1, 4), batch_rows(rows, 5, 1, 0))
    with pytest.raises(ValueError, match="fewer than batch_size"):
        batch_rows(rows[:3], 5, 1, 0)


def test_lr_warms_up_then_decays_to_the_floor() -> None:
    config = TrainConfig(steps=100, lr=1e-3, warmup_steps=10, min_lr_fraction=0.1)
    lrs = np.array([lr_at(config, s) for s in range(100)])
    assert lrs[0] == pytest.approx(1e-4) and lrs[9] == pytest.approx(1e-3)
    assert np.all(np.diff(lrs[:10]) > 0) and np.all(np.diff(lrs[10:]) <= 0)
    assert lrs[-1] == pytest.approx(1e-4, rel=0.01) and lr_at(config, 100) == pytest.approx(1e-4)
    constant = TrainConfig(steps=100, lr=1e-3, warmup_steps=0, schedule="constant")
    assert {lr_at(constant, s) for s in (0, 50, 99)} == {1e-3}


@pytest.mark.parametrize(("field", "value"), [("schedule", "linear"), ("precision", "fp8"), ("grad_clip", 0.0),
                                              ("warmup_steps", -1), ("min_lr_fraction", 1.5)])
def test_bad_optimisation_settings_are_rejected(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        TrainConfig(**{field: value})


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_training_fits_training_windows(split: Split, precision: str) -> None:
    result = train(_config(steps=80, eval_every=40, precision=precision), split)
    assert result.autocast == (None if precision == "fp32" else "bfloat16")
    assert result.windows_per_cpu_s > 0
    assert [r["step"] for r in result.history] == [40, 80]
    final = result.history[-1]
    assert final["test_windows"] == split.test.size
    assert final["train_accuracy"] >= 0.7, result.history
    assert final["train_loss"] < result.history[0]["train_loss"] < 0.75
    assert result.windows_per_s > 0


def test_same_seed_same_weights_other_seed_differs(split: Split) -> None:
    a, b = train(_config(), split), train(_config(), split)
    assert a.param_digest == b.param_digest
    assert train(_config(seed=1), split).param_digest != a.param_digest


def test_resume_continues_exactly(split: Split, tmp_path: Path) -> None:
    # a constant schedule: a cosine one depends on `steps`, which the two parts here change
    straight = train(_config(tmp_path / "straight", schedule="constant"), split)
    first = train(_config(tmp_path / "part", steps=3, schedule="constant"), split)
    ckpt = load_checkpoint(first.checkpoint_path)
    assert ckpt.step == 3 and ckpt.model_config == TINY and ckpt.optimizer_state is not None
    assert ckpt.software_version and ckpt.train_config["lr"] == 1e-2
    resumed = train(_config(tmp_path / "part", schedule="constant"), split, resume=first.checkpoint_path)
    assert resumed.step == 6
    assert resumed.param_digest == straight.param_digest
    metrics = json.loads((tmp_path / "part" / "metrics.json").read_text())
    assert [r["step"] for r in metrics["history"]] == [3, 6]
    assert metrics["train_config"]["model"]["hidden"] == 8
    # a checkpoint at or past --steps has nothing left to train (it ended in "checkpoint not found"
    # naming the new run's folder)
    with pytest.raises(ValueError, match="is at step 6 already: ask for more --steps than that"):
        train(_config(tmp_path / "again", schedule="constant"), split, resume=resumed.checkpoint_path)


def test_resume_with_other_model_config_names_the_mismatch(split: Split, tmp_path: Path) -> None:
    first = train(_config(tmp_path), split)
    with pytest.raises(ValueError, match="hidden: 8 != 4"):
        train(_config(model=ModelConfig(hidden=4, window=4, grid=8)), split, resume=first.checkpoint_path)


def test_data_model_mismatch_is_rejected(split: Split) -> None:
    with pytest.raises(ValueError, match="model expects 5 frames"):
        train(_config(model=ModelConfig(hidden=8, window=5, grid=8)), split)
    for lr in (float("nan"), 0.0, float("inf"), 1e38):  # 1e38: torch's "value cannot be converted to type float"
        with pytest.raises(ValueError, match=rf"TrainConfig.lr must be > 0 and below 3.4e\+37 .*, got {re.escape(str(lr))}$"):
            _config(lr=lr)


def test_the_largest_lr_allowed_trains_into_the_divergence_guard(split: Split) -> None:
    """Just below the bound, Adam's first step is a float32: training runs (a diverging run stops by name)."""
    from fv_algos.slip.train import MAX_LR
    try:
        train(_config(lr=MAX_LR * 0.999, steps=3, eval_every=1, warmup_steps=0), split)
    except ValueError as error:
        assert "training diverged" in str(error)


def test_checkpoint_round_trip_and_classifier(split: Split, tmp_path: Path) -> None:
    result = train(_config(tmp_path), split)
    window = split.windows.get(split.test[:1])[0][0]
    from_path = SlipClassifier(result.checkpoint_path, expected=TINY).predict(window)
    from_model = SlipClassifier(result.model).predict(window)
    assert from_path == pytest.approx(from_model, abs=1e-6)
    model = model_from_checkpoint(load_checkpoint(result.checkpoint_path))
    assert parameter_digest(model) == result.param_digest


def test_checkpoint_errors_are_clear(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="not found"):
        load_checkpoint(tmp_path / "nope.pt")
    real = tmp_path / "real.pt"
    save_checkpoint(real, Checkpoint(ModelConfig(), build_model(ModelConfig()).state_dict(), 0))
    pickled = tmp_path / "pickled.pt"
    pickled.write_bytes(pickle.dumps(object))
    not_models = {"garbage": b"\x00\x01 not a torch file", "text": b"hello", "empty": b"",
                  "text starting with t": b"trial,object,label\n",  # a raw IndexError traceback
                  "cut short": real.read_bytes()[:3000], "pickled object": pickled.read_bytes()}
    for name, data in not_models.items():  # any exception torch.load raises becomes one clear ValueError
        bad = tmp_path / f"{name}.pt"
        bad.write_bytes(data)
        with pytest.raises(ValueError, match="is not a model file that torch.load reads") as err:
            load_checkpoint(bad)
        assert str(bad) in str(err.value) and "weights_only=False" not in str(err.value), name
        assert read_trial_model(bad) is None, name
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    with pytest.raises(ValueError, match="format tag"):
        load_checkpoint(other)
    good = save_checkpoint(tmp_path / "good.pt", Checkpoint(TINY, build_model(TINY).state_dict()))
    with pytest.raises(ValueError, match="grid: 8 != 30"):
        SlipClassifier(good, expected=ModelConfig(hidden=8, window=4))
    wrong_weights = save_checkpoint(tmp_path / "wrong.pt", Checkpoint(TINY, build_model(ModelConfig(hidden=4, window=4, grid=8)).state_dict()))
    with pytest.raises(ValueError, match="do not fit"):
        SlipClassifier(wrong_weights)


def test_main_single_process(split: Split, tmp_path: Path) -> None:
    data = save_sequences(tmp_path / "seq", split.windows.sequences)
    out = tmp_path / "run"
    args = ["--data", str(data), "--out", str(out), "--hidden", "8", "--window", "4", "--steps", "4",
            "--batch-size", "8", "--eval-every", "2", "--no-progress", "--split", "object", "--per-sequence", "3"]
    assert main(args) == 0
    result = json.loads((out / "result_rank0.json").read_text())
    assert result["step"] == 4
    assert load_checkpoint(out / "checkpoint.pt").model_config.grid == 8


def test_training_reads_fields_in_px_of_the_models_frame_width(split: Split, tmp_path: Path) -> None:
    """Fields of frames half as wide (half the px), recorded as such, train the same weights as the
    original fields: training rescales them to the model's ``field_width_px`` as inference does. And
    `fv train` records the data's frame width in the model."""
    def with_width(scale: float, width: int) -> Split:
        s = split.windows.sequences
        scaled = SequenceSet(s.fields.astype(np.float32) * scale, s.labels, s.object_ids, {"frame_width_px": width})
        w = split.windows
        return Split(WindowSet(scaled, w.window, w.sequence, w.start), split.train, split.test, split.kind)
    config = _config(model=replace(TINY, field_width_px=640))
    digests = [parameter_digest(train(config, with_width(scale, width)).model)
               for scale, width in ((1.0, 640), (0.5, 320))]
    assert digests[0] == digests[1]
    data = save_sequences(tmp_path / "seq", with_width(0.5, 320).windows.sequences)
    args = ["--data", str(data), "--out", str(tmp_path / "run"), "--hidden", "8", "--window", "4", "--steps", "2",
            "--batch-size", "8", "--eval-every", "2", "--no-progress", "--per-sequence", "3"]
    assert main(args) == 0
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt").model_config.field_width_px == 320


@pytest.mark.slow
def test_ddp_two_cpu_ranks_stay_identical(split: Split, tmp_path: Path) -> None:
    data = save_sequences(tmp_path / "seq", split.windows.sequences)
    common = ["--data", str(data), "--hidden", "8", "--window", "4", "--steps", "4", "--batch-size", "8",
              "--eval-every", "4", "--no-progress", "--threads", "1", "--per-sequence", "3", "--lr", "0.01",
              "--precision", "fp32"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "fv_algos.slip.train", "--out", str(tmp_path / "ddp"), *common]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ranks = [json.loads((tmp_path / "ddp" / f"result_rank{r}.json").read_text()) for r in (0, 1)]
    assert ranks[0]["param_digest"] == ranks[1]["param_digest"]
    assert ranks[0]["step"] == ranks[1]["step"] == 4
    ddp_model = model_from_checkpoint(load_checkpoint(tmp_path / "ddp" / "checkpoint.pt"))
    assert parameter_digest(ddp_model) == ranks[0]["param_digest"]
    # two half batches with averaged gradients = one full batch: same weights as a single process
    assert main(["--out", str(tmp_path / "single"), *common]) == 0
    single = model_from_checkpoint(load_checkpoint(tmp_path / "single" / "checkpoint.pt"))
    for (name, a), b in zip(single.state_dict().items(), ddp_model.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-5), name


def test_a_diverging_run_stops_with_an_error_instead_of_scoring_nan_as_no_slip(split: Split, tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """NaN logits' argmax is class 0: a NaN model was scored at the test set's no-slip share (1.0 on an
    all-held test set) and saved; the run now stops at the first step whose parameters are not finite. Whether
    a given lr diverges depends on the processor's kernels (lr 1e30 made the parameters NaN on one machine and
    left a dead, finite network on another), so the optimizer's third step leaves a NaN here."""
    adam_step = torch.optim.Adam.step
    steps = []

    def diverging(self: torch.optim.Adam, *args: object, **kwargs: object) -> object:
        out = adam_step(self, *args, **kwargs)
        steps.append(None)
        if len(steps) == 3:
            with torch.no_grad():
                self.param_groups[0]["params"][0].fill_(float("nan"))
        return out

    monkeypatch.setattr(torch.optim.Adam, "step", diverging)
    with pytest.raises(ValueError, match=r"training diverged at step 3: .*lr 0.01: try a lower one") as error:
        train(_config(tmp_path, steps=20, eval_every=1, warmup_steps=0), split)
    if (tmp_path / "checkpoint.pt").exists():  # written at a step before it diverged: finite weights
        assert "keeps step" in str(error.value)
        state = load_checkpoint(tmp_path / "checkpoint.pt").model_state
        assert all(bool(torch.isfinite(t).all()) for t in state.values())
