"""`fv dataset sim` (simulated slip dataset), `fv train` (train a slip classifier) and
`fv eval` (the paper's Table 1 per split, and the speed/accuracy variants)."""
from __future__ import annotations

import argparse
import json
import os
import shlex
import time
from pathlib import Path

from nodes.arg_types import output_file, output_folder, output_with_suffix, positive_float, positive_int, random_seed
from nodes.real_commands import crop_flags, online_flags
from nodes.shipped_models import model_help

SPLITS = {"sequence": "sequence", "paper": "random", "object": "object"}
"""CLI split name -> fv_algos.slip.windows split kind ("paper" = the paper's random windows)."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dataset", help="generate slip datasets")
    kinds = p.add_subparsers(dest="dataset_kind", required=True, metavar="KIND")
    q = kinds.add_parser("sim", help="simulated sequences through the real perception pipeline (paper protocol)")
    q.add_argument("--out", type=output_with_suffix(".npz"), required=True, help="output .npz (float16 fields)")
    q.add_argument("--sequences", type=int, default=1600, help="raw sequences, half slip (default 1600); with "
                   "--grasps, the grasps")
    q.add_argument("--grasps", action="store_true", help="whole grasps as the main job plays them (pressed from rest, "
                   "2 or 4 s of a scenario, released), cut into sequences of --frames every 10 frames, every frame "
                   "labelled with its truth: extra training data for `fv train --extra`")
    q.add_argument("--frames", type=int, default=15, help="frames per sequence (default 15)")
    q.add_argument("--fps", type=float, default=15.0, help="frame rate, Hz (default 15)")
    q.add_argument("--seed", type=random_seed, default=0, help="master seed (default 0)")
    q.add_argument("--workers", type=positive_int, default=2, help="worker processes (default 2)")
    q.add_argument("--preset", default="default", help="perception preset: paper, default, fastest")
    q.add_argument("--no-progress", action="store_true", help="no progress bar")
    q.set_defaults(func=_dataset_sim)

    p = sub.add_parser("train", help="train a slip classifier (works under torchrun: DDP)")
    p.add_argument("--data", type=Path, required=True, help="sequence dataset .npz (fv dataset sim)")
    p.add_argument("--extra", type=Path, default=None, help="a second dataset whose windows only add to the training "
                   "rows (whole grasps: fv dataset sim --grasps); the split and test rows stay --data's")
    p.add_argument("--out", type=output_folder, required=True,
                   help="run folder: checkpoint.pt, metrics.json, run.json, curve.png")
    _model_flags(p)
    p.add_argument("--steps", type=int, default=None, help="optimizer steps (default: TrainConfig's)")
    p.add_argument("--resume", type=Path, default=None, help="checkpoint to continue from")
    p.add_argument("--eval-every", type=int, default=None, help="steps between evaluations (default: TrainConfig's)")
    p.add_argument("--export", type=output_with_suffix(".pt"), default=None,
                   help="also write an inference-only checkpoint here (no optimizer state) and its .json record")
    p.add_argument("--force", action="store_true", help="train afresh into an --out that holds a trained run")
    p.set_defaults(func=_train)

    p = sub.add_parser("eval", help="Table 1 (every split and model) and the speed/accuracy variants; or, with "
                       "--trials, one model on a folder of labelled real recordings")
    mode = p.add_mutually_exclusive_group()  # three evaluations: Table 1, real recordings, the main job's stream
    mode.add_argument("--data", type=Path, help="sequence dataset .npz (fv dataset sim)")
    p.add_argument("--out", type=output_folder, help="report folder: table1.json, variants.json, pareto.png")
    mode.add_argument("--trials", type=Path, help="folder with labels.csv (trial,object,label) and <trial>/camera_0.avi "
                   "[camera_2.avi] (or .mp4, .mkv, .mov, .m4v): judge --model on it, from video to decision")
    p.add_argument("--model", help=f"with --trials or --stream: {model_help()}")
    mode.add_argument("--stream", type=positive_float, metavar="SECONDS",
                   help="judge a window --model frame by frame on SECONDS of the simulated camera's random grasps "
                        "(the main job's stream) against the simulator's truth; --fps, --seed set the camera")
    p.add_argument("--fps", type=positive_float, default=None, help=f"with --stream: camera rate, Hz (default "
                   f"{STREAM_FPS:g}, the pipeline's; a video's rate is labels.csv's fps column, else its container's)")
    p.add_argument("--cache", type=Path, help="with --trials: folder to cache the fields in (default: none)")
    p.add_argument("--workers", type=positive_int, default=2,
                   help="with --trials: processes for the fields (default 2)")
    crop_flags(p)
    online_flags(p)
    p.add_argument("--models", type=Path, default=None,
                   help="checkpoint folder: DIR/<split>_<model>[_variant]/ as fv train writes; missing ones are "
                        "trained there (default OUT/models)")
    p.add_argument("--splits", default=",".join(SPLITS), help="comma-separated splits among sequence, paper, "
                   "object (default all)")
    p.add_argument("--models-list", default="convlstm,cnn_lstm,lstm", help="comma-separated learned models")
    _model_flags(p, single_run=False)
    p.add_argument("--steps", type=int, default=None, help="steps for models that must be trained (default: TrainConfig's)")
    p.add_argument("--no-variants", action="store_true", help="skip the variants table and Pareto plot")
    p.add_argument("--timing-threads", type=positive_int, default=2, help="torch threads for the ms/window timing (default 2)")
    p.add_argument("--repeats", type=positive_int, default=50, help="timed calls per ms/window figure (default 50)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_eval)
    p.set_defaults(option_defaults={dest: p.get_default(dest) for dest in _EVAL_OPTIONS})


STREAM_FPS = 30.0  # Hz: `fv eval --stream`'s camera rate by default, the pipeline's
# The options each of fv eval's three evaluations reads, beside --json: one given to another is refused by name, as
# it would be ignored (`--fps 50` with --trials judged a 50 fps camera's frames at its container's 25 fps).
_EVAL_READS = {
    "data": frozenset({"out", "models", "splits", "models_list", "hidden", "kernel", "window", "lr", "batch",
                       "precision", "seed", "test_fraction", "threads", "device", "no_progress", "steps",
                       "no_variants", "timing_threads", "repeats"}),
    "trials": frozenset({"model", "cache", "workers", "crop", "size", "online", "alarm", "plot", "no_progress"}),
    "stream": frozenset({"model", "fps", "seed"}),
}
_EVAL_OPTIONS = frozenset().union(*_EVAL_READS.values())


def _refuse_unread(args: argparse.Namespace, mode: str) -> None:
    """Refuse, naming each and the evaluations that read it, the options given to fv eval (other than their
    defaults) that its ``mode`` evaluation ("data", "trials" or "stream") does not read."""
    unread = sorted(dest for dest in _EVAL_OPTIONS - _EVAL_READS[mode]
                    if getattr(args, dest) != args.option_defaults[dest])
    if not unread:
        return
    readers = {dest: " or ".join(f"--{m}" for m, reads in _EVAL_READS.items() if dest in reads) for dest in unread}
    named = "; ".join(f"--{dest.replace('_', '-')} (read with {modes})" for dest, modes in readers.items())
    hint = (": a video's frame rate is the fps column of labels.csv, else its container's"
            if mode == "trials" and "fps" in unread else "")
    raise ValueError(f"fv eval --{mode} does not read {named}; given, it would be ignored{hint}")


def _eval_stream(args: argparse.Namespace) -> int:
    """`fv eval --stream S --model M [--fps F] [--seed N] [--json]`: :func:`fv_algos.slip.stream.judge_stream`."""
    from fv_algos.slip.classifier import SlipClassifier
    from fv_algos.slip.stream import judge_stream
    from nodes.shipped_models import model_path
    if not args.model:
        raise ValueError("--stream needs --model (a shipped window model such as sim_cnn_lstm, or a checkpoint)")
    started = time.perf_counter()
    fps = STREAM_FPS if args.fps is None else args.fps
    scores = judge_stream(SlipClassifier(model_path(args.model), threads=1), args.stream, fps, args.seed)
    report = {"model": args.model, "fps": fps, "seconds": args.stream, "seed": args.seed, **scores,
              "wall_s": time.perf_counter() - started}
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    held, slipping = ("-" if scores[key] is None else f"{scores[key]:.3f}"
                      for key in ("held_called_slip", "slip_called_slip"))
    print(f"{args.model} at {fps:g} fps, {report['frames_judged']} frames (seed {args.seed}): accuracy "
          f"{report['accuracy']:.3f}, held frames called slip {held}, slipping frames called slip {slipping} "
          f"({report['wall_s']:.0f} s)")
    for action, row in report["phases"].items():
        print(f"  {action:8s} {row['frames']:5d} frames, slip {row['slip_share']:.2f}, accuracy {row['accuracy']:.3f}")
    lag = report["transition"]
    steady, changing, before = ("-" if lag[key] is None else f"{lag[key]:.3f}"
                                for key in ("steady_accuracy", "accuracy", "slip_before_called_slip"))
    print(f"  windows whose truth changes within them: {lag['share']:.2f} of the frames, accuracy {changing} "
          f"(the others {steady}); held at their last field after slip, called slip {before}")
    return 0


def _model_flags(p: argparse.ArgumentParser, single_run: bool = True) -> None:
    """Flags shared by `fv train` (single_run) and `fv eval`; None means the library default."""
    if single_run:
        p.add_argument("--split", choices=list(SPLITS), default="sequence",
                       help="sequence: whole sequences held out; paper: random windows (the paper's, leaky); "
                            "object: whole objects held out (default sequence)")
        p.add_argument("--model", default="convlstm", help="convlstm (paper), cnn_lstm or lstm (default convlstm)")
    p.add_argument("--hidden", type=int, default=64, help="hidden channels / units (default 64)")
    p.add_argument("--kernel", type=int, default=3, help="ConvLSTM kernel (default 3: the paper's 269,826 params)")
    p.add_argument("--window", type=int, default=10, help="frames per window (default 10)")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate (default: TrainConfig's)")
    p.add_argument("--batch", type=int, default=None, help="global batch (default: TrainConfig's)")
    p.add_argument("--precision", choices=("auto", "fp32", "bf16"), default=None,
                   help="training arithmetic: auto = bf16 autocast on CPUs with native bf16 (AMX/AVX512-BF16), "
                        "else fp32 (default: TrainConfig's)")
    p.add_argument("--seed", type=random_seed, default=0, help="training and split seed (default 0)")
    p.add_argument("--test-fraction", type=float, default=0.1, help="held-out share (default 0.1)")
    p.add_argument("--threads", type=positive_int, default=None, help="torch threads for training")
    p.add_argument("--device", default="cpu", help="torch device to train on: cpu (default), cuda, cuda:N, mps, "
                   "xpu[:N]; under torchrun, cuda means each rank's own GPU")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


_NOT_FLAGS = ("func", "command", "dataset_kind", "verbose")


def command_line(args: argparse.Namespace) -> str:
    """The command as a shell string with every option spelled out, defaults included (for
    provenance records: it reproduces the run whatever the defaults become)."""
    words = ["fv", args.command] + ([args.dataset_kind] if getattr(args, "dataset_kind", None) else [])
    for key, value in vars(args).items():
        if key in _NOT_FLAGS or value is None or value is False:
            continue
        words += [f"--{key.replace('_', '-')}"] + ([] if value is True else [str(value)])
    return shlex.join(words)


def _dataset_sim(args: argparse.Namespace) -> int:
    from collections import Counter

    from fv_algos.sim_dataset import SimDatasetConfig, fields_nbytes, generate
    from fv_algos.slip.windows import save_sequences
    config = SimDatasetConfig(n_sequences=args.sequences, n_frames=args.frames, fps=args.fps, seed=args.seed,
                              preset=args.preset, grasps=args.grasps)
    needed, available = fields_nbytes(config), os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    if needed == 0:  # said after every grasp had been simulated
        raise ValueError(f"--frames {args.frames}: every grasp is shorter at {args.fps:g} fps; give fewer frames")
    if needed > available:  # it simulated until the memory ran out
        raise ValueError(f"--sequences {args.sequences} of {args.frames} frames need up to {needed / 1e9:.1f} GB "
                         f"of fields in memory; {available / 1e9:.1f} GB is free: make fewer, in several sets")
    started = time.perf_counter()
    sequences = generate(config, workers=args.workers, progress=not args.no_progress)
    sequences.metadata["command"] = command_line(args)
    path = save_sequences(args.out, sequences)
    kinds = Counter(sequences.metadata["kinds"])
    source = f"from {args.sequences} grasps, {int(sequences.labels.sum())} with slipping frames" if args.grasps else \
        f"{int(sequences.labels.sum())} slip"
    print(f"wrote {len(sequences.labels)} sequences ({source}) of "
          f"{sequences.n_frames} frames to {path} ({path.stat().st_size / 1e6:.1f} MB) in "
          f"{time.perf_counter() - started:.1f} s; kinds {dict(sorted(kinds.items()))}; "
          f"invalid fields {sequences.metadata['invalid_frames']}")
    return 0


RUN_RECORD = "run.json"
CURVE_PNG = "curve.png"


def _write_run(out: Path, *, command: str, data: Path, fingerprint: str, split: str, seed: int, test_fraction: float,
               model_config: dict, params: int, history: list[dict], wall_s: float, windows_per_s: float,
               dataset_metadata: dict, lr: float, batch_size: int, resumed_from: Path | None = None,
               windows_per_cpu_s: float | None = None, autocast: str | None = None,
               extra: tuple[Path, str] | None = None) -> dict:
    """Write run.json (provenance and final metrics) and curve.png (accuracy and loss vs step,
    like the paper's Fig. 7) into ``out``; returns the record. wall_s is this invocation's time;
    wall_s_total adds the wall_s_total of the run resumed from (its folder's run.json).
    windows_per_cpu_s (training windows per CPU-second per torch thread) estimates the
    quiet-machine windows_per_s when other processes share the cores; autocast is the training
    autocast dtype (None: fp32); extra is the (path, fingerprint) of the training-only dataset, if any."""
    from nodes.plots import curve_plot
    if not history:
        raise ValueError(f"training in {out} recorded no evaluation")
    final = history[-1]
    record = {
        "command": command, "data": str(data), "data_fingerprint": fingerprint,
        "dataset_seed": dataset_metadata.get("config", {}).get("seed", dataset_metadata.get("seed")),
        "split": split, "split_kind": SPLITS[split], "split_seed": seed, "test_fraction": test_fraction,
        "model_config": model_config, "params": params, "steps": int(final["step"]), "lr": lr, "batch_size": batch_size,
        "test_accuracy": final["test_accuracy"], "test_windows": final["test_windows"],
        "train_accuracy": final["train_accuracy"], "wall_s": round(wall_s, 1),
        "wall_s_total": round(wall_s + _previous_wall_s(resumed_from), 1), "windows_per_s": round(windows_per_s, 2),
        "windows_per_cpu_s": None if windows_per_cpu_s is None else round(windows_per_cpu_s, 2), "autocast": autocast,
        "resumed_from": None if resumed_from is None else str(resumed_from),
        **({} if extra is None else {"extra_data": str(extra[0]), "extra_fingerprint": extra[1]}),
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / RUN_RECORD).write_text(json.dumps(record, indent=1))
    steps = [r["step"] for r in history]
    series = {name.replace("_", " "): (steps, [r[name] for r in history])
              for name in ("train_accuracy", "test_accuracy", "train_loss", "test_loss")}
    curve_plot(series, out / CURVE_PNG, title=f"{model_config['arch']} on the {split} split",
               x_label="optimizer step", y_label="accuracy / cross-entropy")
    return record


def _previous_wall_s(resumed_from: Path | None) -> float:
    """wall_s_total recorded next to a checkpoint being resumed (0 when none is recorded)."""
    record = None if resumed_from is None else resumed_from.parent / RUN_RECORD
    if record is None or not record.is_file():
        return 0.0
    previous = json.loads(record.read_text())
    return float(previous.get("wall_s_total", previous.get("wall_s", 0.0)))


PAPER_WINDOWS_PER_SEQUENCE = 5


def _per_sequence(n_frames: int, window: int) -> int:
    """Windows cut from each sequence: the paper's 5, or as many as fit in shorter sequences."""
    if n_frames < window:
        raise ValueError(f"sequences have {n_frames} frames, fewer than --window {window}")
    return min(PAPER_WINDOWS_PER_SEQUENCE, n_frames - window + 1)


def _split(sequences, split: str, window: int, test_fraction: float, seed: int):
    """Windows of ``window`` frames (see _per_sequence) and the named split of them."""
    from fv_algos.slip.windows import make_windows, split_windows
    windows = make_windows(sequences, window=window, per_sequence=_per_sequence(sequences.n_frames, window))
    return split_windows(windows, SPLITS[split], test_fraction, seed)


def _train(args: argparse.Namespace) -> int:
    from fv_algos.slip import train as slip_train
    from fv_algos.slip.classifier import load_checkpoint
    from fv_algos.slip.models import ModelConfig, build_model, count_parameters, usable_device
    from fv_algos.slip.windows import load_sequences
    from fv_algos.slip_study import dataset_fingerprint
    if (args.out / slip_train.CHECKPOINT_NAME).is_file() and args.resume is None and not args.force:
        raise ValueError(f"{args.out} holds a trained run: --resume {args.out / slip_train.CHECKPOINT_NAME} to go "
                         "on with it, --force to replace it, or choose another --out")
    usable_device(args.device)  # before the data set is read
    sequences = load_sequences(args.data)
    # validate here: train.main's own parser would exit instead of raising a clear ValueError
    ModelConfig(arch=args.model, hidden=args.hidden, kernel=args.kernel, window=args.window, grid=sequences.grid)
    extra = None if args.extra is None else load_sequences(args.extra)
    if extra is not None and dataset_fingerprint(extra) == dataset_fingerprint(sequences):
        raise ValueError(f"--extra {args.extra} holds --data's own sequences: its test windows would be trained on")
    optional = {"--steps": args.steps, "--lr": args.lr, "--batch-size": args.batch, "--eval-every": args.eval_every,
                "--threads": args.threads, "--resume": args.resume, "--precision": args.precision,
                "--extra": args.extra, "--device": args.device}
    argv = ["--data", str(args.data), "--out", str(args.out), "--split", SPLITS[args.split], "--arch", args.model,
            "--hidden", str(args.hidden), "--kernel", str(args.kernel), "--window", str(args.window),
            "--seed", str(args.seed), "--test-fraction", str(args.test_fraction),
            "--per-sequence", str(_per_sequence(sequences.n_frames, args.window))]
    argv += [item for flag, value in optional.items() if value is not None for item in (flag, str(value))]
    argv += ["--no-progress"] if args.no_progress else []
    started = time.perf_counter()
    slip_train.main(argv, sequences, extra)
    wall_s = time.perf_counter() - started
    if int(os.environ.get("RANK", "0")) != 0:
        return 0
    checkpoint = load_checkpoint(args.out / slip_train.CHECKPOINT_NAME)
    result = json.loads((args.out / "result_rank0.json").read_text())
    record = _write_run(
        args.out, command=command_line(args), data=args.data, fingerprint=dataset_fingerprint(sequences),
        split=args.split, seed=args.seed, test_fraction=args.test_fraction, model_config=checkpoint.model_config.to_dict(),
        params=count_parameters(build_model(checkpoint.model_config)), history=checkpoint.history, wall_s=wall_s,
        windows_per_s=result["windows_per_s"], dataset_metadata=sequences.metadata, resumed_from=args.resume,
        lr=checkpoint.train_config["lr"], batch_size=checkpoint.train_config["batch_size"],
        windows_per_cpu_s=result.get("windows_per_cpu_s"), autocast=result.get("autocast"),
        extra=None if extra is None else (args.extra, dataset_fingerprint(extra)))
    print(f"{record['model_config']['arch']} on the {args.split} split: test accuracy "
          f"{record['test_accuracy']:.4f} on {record['test_windows']} windows after {record['steps']} steps, "
          f"{wall_s:.0f} s -> {args.out}")
    if args.export is not None:
        _export(checkpoint, record, args.export)
    return 0


def _export(checkpoint, record: dict, path: Path) -> None:
    """Inference-only copy of ``checkpoint`` at ``path`` (.pt) and ``record`` next to it (.json)."""
    from dataclasses import replace

    from fv_algos.slip.classifier import save_checkpoint
    save_checkpoint(path, replace(checkpoint, optimizer_state=None))
    path.with_suffix(".json").write_text(json.dumps(record, indent=1))
    print(f"exported inference-only checkpoint {path} ({path.stat().st_size / 1e6:.2f} MB) "
          f"and {path.with_suffix('.json')}")


TABLE_COLUMNS = ["model", "split", "accuracy", "f1", "params", "ms_per_window", "n", "source"]
VARIANT_COLUMNS = ["model", "variant", "accuracy", "f1", "params", "ms_per_window", "source"]
VARIANT_KINDS = ("fp32", "int8", "bf16")


class _ModelStore:
    """Trained models of one `fv eval` run: loaded from DIR/<key>/checkpoint.pt when there (its
    run.json must name the same data, split and seed), else trained and written there."""

    def __init__(self, folder: Path, data: Path, sequences, args: argparse.Namespace) -> None:
        from fv_algos.slip_study import dataset_fingerprint
        self.folder, self.data, self.sequences, self.args = folder, data, sequences, args
        self.fingerprint = dataset_fingerprint(sequences)
        self.sources: dict[str, str] = {}
        self.models: dict[str, object] = {}

    def get(self, key: str, split_name: str, config, split, sequences=None):
        """The model named ``key`` for ModelConfig ``config`` on Split ``split``."""
        from fv_algos.slip.classifier import load_checkpoint, model_from_checkpoint
        from fv_algos.slip.models import count_parameters
        from fv_algos.slip.train import CHECKPOINT_NAME, TrainConfig, train
        from fv_algos.slip_study import dataset_fingerprint
        if key in self.models:
            return self.models[key]
        a, run_dir = self.args, self.folder / key
        fingerprint = self.fingerprint if sequences is None else dataset_fingerprint(sequences)
        given = {"steps": a.steps, "batch_size": a.batch, "lr": a.lr, "threads": a.threads, "precision": a.precision}
        train_config = TrainConfig(model=config, seed=a.seed, out_dir=str(run_dir), progress=not a.no_progress,
                                   device=a.device, **{k: v for k, v in given.items() if v is not None})
        if (run_dir / CHECKPOINT_NAME).is_file():
            if not (run_dir / RUN_RECORD).is_file():
                raise ValueError(f"{run_dir}: its training did not finish (no {RUN_RECORD}): remove it or point "
                                 "--models elsewhere")
            record = json.loads((run_dir / RUN_RECORD).read_text())
            wanted = {"data_fingerprint": fingerprint, "split": split_name, "split_seed": a.seed,
                      "test_fraction": a.test_fraction, "steps": train_config.steps, "lr": train_config.lr,
                      "batch_size": train_config.batch_size}  # --steps 20 must not reuse a 2-step model
            wrong = {k: (record.get(k), v) for k, v in wanted.items() if record.get(k) != v}
            if wrong:
                raise ValueError(f"{run_dir} was not trained on this data, split and settings ({RUN_RECORD} has, vs "
                                 f"wanted: {wrong}); remove it or point --models elsewhere")
            self.sources[key] = f"checkpoint {run_dir / CHECKPOINT_NAME}"
            self.models[key] = model_from_checkpoint(load_checkpoint(run_dir / CHECKPOINT_NAME, expected=config))
            return self.models[key]
        started = time.perf_counter()
        result = train(train_config, split)
        _write_run(run_dir, command=command_line(a), data=self.data, fingerprint=fingerprint, split=split_name,
                   seed=a.seed, test_fraction=a.test_fraction, model_config=config.to_dict(),
                   params=count_parameters(result.model),
                   history=result.history, wall_s=time.perf_counter() - started, windows_per_s=result.windows_per_s,
                   dataset_metadata=self.sequences.metadata, windows_per_cpu_s=result.windows_per_cpu_s,
                   autocast=result.autocast, lr=train_config.lr, batch_size=train_config.batch_size)
        self.sources[key] = f"trained {train_config.steps} steps -> {run_dir}"
        self.models[key] = result.model.cpu()  # judged and timed on the cpu, wherever it was trained
        return self.models[key]


def _eval(args: argparse.Namespace) -> int:
    _refuse_unread(args, "stream" if args.stream is not None else "trials" if args.trials is not None else "data")
    if args.stream is not None:
        return _eval_stream(args)
    if args.trials is not None:
        from nodes.real_commands import eval_trials_command
        if not args.model:
            raise ValueError("--trials needs --model (a shipped name such as gelsight, or a checkpoint)")
        return eval_trials_command(args)
    if args.data is None or args.out is None:
        raise ValueError("give --data DATASET.npz and --out DIR (or --trials DIR --model M)")
    from fv_algos.slip.evaluate import table_rows
    from fv_algos.slip.models import ModelConfig, usable_device
    from fv_algos.slip.windows import load_sequences
    from fv_algos.slip_study import split_inflation, table_predictors
    from nodes.plots import markdown_table, pareto_plot
    splits, archs = _csv(args.splits, str), _csv(args.models_list, str)
    unknown = sorted(set(splits) - set(SPLITS))
    if unknown:
        raise ValueError(f"--splits: unknown {unknown} (known: {list(SPLITS)})")
    usable_device(args.device)  # before the data set is read
    sequences = load_sequences(args.data)
    store = _ModelStore(args.models or args.out / "models", args.data, sequences, args)
    base = {"hidden": args.hidden, "kernel": args.kernel, "window": args.window, "grid": sequences.grid,
            "field_width_px": sequences.frame_width_px}
    table, splits_done = [], {}
    for split_name in splits:
        split = _split(sequences, split_name, args.window, args.test_fraction, args.seed)
        models = {arch: store.get(f"{split_name}_{arch}", split_name, ModelConfig(arch=arch, **base), split)
                  for arch in archs}
        rows = table_rows(table_predictors(models, split), split, args.timing_threads, args.repeats)
        for row in rows:
            row.update(split=split_name, source=store.sources.get(f"{split_name}_{row['model']}", "fitted on train"))
        table += rows
        splits_done[split_name] = split
    report = {"data": str(args.data), "data_fingerprint": store.fingerprint, "seed": args.seed, "table1": table,
              "paper_split_inflation": split_inflation(table, "paper", "sequence")}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "table1.json").write_text(json.dumps(report, indent=1))
    if args.no_variants:  # an earlier run's, which this report would otherwise seem to include
        for stale in ("variants.json", "pareto.png"):
            (args.out / stale).unlink(missing_ok=True)
    else:
        report["variants"] = _variants(args, sequences, store, splits_done, base)
        (args.out / "variants.json").write_text(json.dumps(report["variants"], indent=1))
        pareto_plot(report["variants"], "ms_per_window", "accuracy", "label", args.out / "pareto.png",
                    title=f"ConvLSTM variants, {_VARIANT_SPLIT} split ({args.timing_threads} threads)",
                    x_label="ms per window (batch 1)", y_label="test accuracy")
    if args.json:
        print(json.dumps(report, indent=1))
        return 0
    print(markdown_table(table, TABLE_COLUMNS))
    print("\npaper (random-window) split minus by-sequence split accuracy:",
          json.dumps({k: round(v, 4) for k, v in report["paper_split_inflation"].items()}))
    if "variants" in report:
        print("\n" + markdown_table(report["variants"], VARIANT_COLUMNS))
    print(f"\nreport in {args.out}")
    return 0


_VARIANT_SPLIT = "sequence"


def _variants(args: argparse.Namespace, sequences, store: _ModelStore, splits: dict, base: dict) -> list[dict]:
    """ConvLSTM variants on the sequence split: hidden H, H/2, H/4; window W, W/2; grid G, 2G/3,
    each in fp32, int8 and bf16 (defaults H=64, W=10, G=30: the paper's 64/32/16, 10/5, 30/20)."""
    from fv_algos.slip.evaluate import variant_rows
    from fv_algos.slip.models import ModelConfig
    from fv_algos.slip_study import resample_grid
    split_name = _VARIANT_SPLIT
    split = splits.get(split_name) or _split(sequences, split_name, args.window, args.test_fraction, args.seed)
    h, w, g = base["hidden"], base["window"], base["grid"]
    half, small = max(1, w // 2), max(2, round(2 * g / 3))
    coarse_sequences = resample_grid(sequences, small)
    short = _split(sequences, split_name, half, args.test_fraction, args.seed)
    coarse = _split(coarse_sequences, split_name, w, args.test_fraction, args.seed)
    plan = [(f"_h{hidden}", {"hidden": hidden}, split, None) for hidden in (max(1, h // 2), max(1, h // 4))]
    plan = [("", {}, split, None), *plan, (f"_w{half}", {"window": half}, short, None),
            (f"_g{small}", {"grid": small}, coarse, coarse_sequences)]
    entries, keys = [], {}
    for suffix, change, variant_split, variant_sequences in plan:
        config = ModelConfig(**{**base, **change})
        name, key = f"h{config.hidden} w{config.window} g{config.grid}", f"{split_name}_convlstm{suffix}"
        entries.append((name, store.get(key, split_name, config, variant_split, variant_sequences), variant_split))
        keys[name] = key
    rows = variant_rows(entries, VARIANT_KINDS, args.timing_threads, args.repeats)
    for row in rows:
        row.update(label=f"{row['model']} {row['variant']}", source=store.sources[keys[row["model"]]])
    return rows


def add_bench_parser(kinds: argparse._SubParsersAction, name: str) -> None:
    """`fv bench slip`: inference time per window of a slip checkpoint in each variant and, with --data,
    each variant's accuracy and F1 on every window of that data set."""
    p = kinds.add_parser(name, help="slip classifier inference speed per variant (fp32, bf16, int8), and with "
                         "--data its accuracy")
    p.add_argument("--model", default="sim", help=f"{model_help()} (default sim)")
    p.add_argument("--variants", default=None, help="comma-separated variants (fp32,bf16,int8,compile; default "
                   "fp32,bf16,int8 on the cpu, fp32,bf16 elsewhere: int8 runs on the cpu only)")
    p.add_argument("--threads", default="1,2", help="comma-separated torch thread counts (default 1,2)")
    p.add_argument("--repeats", type=positive_int, default=50, help="timed calls per measurement (default 50)")
    p.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:N, mps, xpu[:N]")
    p.add_argument("--data", type=Path, default=None, help="sequence dataset .npz (fv dataset sim) the model was "
                   "not trained on: each variant's accuracy and F1 on every window of it, beside its speed")
    p.add_argument("--json", action="store_true", help="print the rows as JSON")
    p.set_defaults(func=_bench_slip)


def _bench_slip(args: argparse.Namespace) -> int:
    import numpy as np

    from fv_algos.slip.classifier import load_checkpoint, model_from_checkpoint
    from fv_algos.slip.evaluate import evaluate_rows, model_windows, time_forward, variant_predictor
    from fv_algos.slip.models import count_parameters
    from fv_algos.slip.windows import load_sequences
    from nodes.plots import markdown_table
    from nodes.shipped_models import model_path
    model = model_from_checkpoint(load_checkpoint(model_path(args.model)))
    cfg = model.config
    window = np.zeros((1, cfg.window, cfg.grid, cfg.grid, 3), np.float32)
    rows = []
    thread_counts = _csv(args.threads, int)
    if min(thread_counts) < 1:
        raise ValueError(f"--threads {args.threads}: every thread count must be >= 1")
    variants = args.variants or ("fp32,bf16,int8" if args.device == "cpu" else "fp32,bf16")
    windows = None if args.data is None else model_windows(load_sequences(args.data), cfg, f"--data {args.data}")
    for variant in _csv(variants, str):
        predictor = variant_predictor(model, variant, args.device)
        scores = {}
        if windows is not None:
            metrics = evaluate_rows(predictor, windows, np.arange(len(windows)))
            scores = {"accuracy": metrics.accuracy, "f1": metrics.f1, "windows": metrics.n}
        for threads in thread_counts:
            rows.append({"model": args.model, "variant": variant, "device": args.device, "threads": threads,
                         "params": count_parameters(model),
                         "ms_per_window": time_forward(predictor, window, threads, args.repeats), **scores})
    print(json.dumps(rows, indent=1) if args.json else markdown_table(rows, list(rows[0])))
    return 0


def _csv(text: str, kind: type) -> list:
    """'a,b' -> [kind('a'), kind('b')]; ValueError naming the bad item."""
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise ValueError(f"empty list {text!r}")
    try:
        return [kind(t) for t in items]
    except ValueError as exc:
        raise ValueError(f"bad item in {text!r}: {exc}") from exc
