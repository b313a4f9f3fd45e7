"""`fv real ...` (fields, cross-validation and training on real labelled grasp trials) and
`fv eval-trials` (a trained slip model judged on a folder of real trials, video to decision).

Two methods (`--method`): `trial` (default), the trial-level temporal network on per-frame
contact-motion and field descriptors of :mod:`fv_algos.trial_net`, shipped as
`fv_algos/weights/slip_gelsight_trial.pt`; `windows`, the paper's window classifiers (ConvLSTM and
variants, :mod:`fv_algos.trial_eval`), shipped as `fv_algos/weights/slip_gelsight_windows.pt`.
`fv eval --trials DIR --model NAME` judges the shipped model NAME (`gelsight` is `gelsight_trial`) or a checkpoint.

A trials folder holds `labels.csv` (columns trial, object, label = slip / no_slip) and per trial
`<trial>/camera_0.avi` (+ `camera_2.avi`; or .mp4, .mkv, .mov, .m4v). Fields are cached per video under
`--cache` (default ~/.cache/fingervision/real_fields), never inside the repository."""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING

from nodes.arg_types import output_file, output_with_suffix, positive_float, positive_int, random_seed
from nodes.shipped_models import model_help

log = logging.getLogger(__name__)

if TYPE_CHECKING:  # torch is imported only where a model is used
    from fv_algos.contact_motion import ContactMotionParams
    from fv_algos.frame_crop import FrameCrop
    from fv_algos.real_trials import Trial, TrialFields
    from fv_algos.trial_net import TrialModel

DEFAULT_CACHE = Path.home() / ".cache" / "fingervision" / "real_fields"


def register(sub: argparse._SubParsersAction) -> None:
    real = sub.add_parser("real", help="slip detection on real labelled grasp trials (fields, cv, train)")
    verbs = real.add_subparsers(dest="real_command", required=True, metavar="VERB")

    p = verbs.add_parser("fields", help="fields of every trial video (cached) and tracking quality")
    _data_args(p)
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_fields)

    p = verbs.add_parser("cv", help="object-held-out cross-validation (window and trial accuracy per fold)")
    _data_args(p)
    _fit_args(p, window_steps=300)
    p.add_argument("--folds", type=int, default=5, help="object folds (default 5; the number of objects, "
                   "e.g. 29, leaves one object out)")
    online_flags(p)
    p.add_argument("--out", type=output_file, default=None, help="also write the full report (JSON) here")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_cv)

    p = verbs.add_parser("train", help="train on all trials and write a shipped-model checkpoint + JSON")
    _data_args(p)
    _fit_args(p, window_steps=600)
    p.add_argument("--out", type=output_with_suffix(".pt"), required=True,
                   help="checkpoint path, e.g. fv_algos/weights/slip_gelsight_windows.pt (its record: the .json beside it)")
    p.add_argument("--cv-report", type=_cv_report, default=None, help="`fv real cv --out` report to record beside it")
    p.set_defaults(func=_train)

    p = sub.add_parser("eval-trials", help="judge a slip model on a folder of real trials (video to decision)")
    p.add_argument("--model", required=True, help=model_help())
    p.add_argument("--trials", type=Path, required=True,
                   help="folder with labels.csv and <trial>/camera_0.avi (or .mp4, .mkv, .mov, .m4v)")
    p.add_argument("--cache", type=Path, default=None, help="reuse / write cached fields here (default: none)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="processes for the fields and contact motion (default 1)")
    crop_flags(p)
    online_flags(p)
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=eval_trials_command)


def crop_flags(p: argparse.ArgumentParser) -> None:
    """--crop and --size: every frame of the trials' videos cut and resized as it is read (raw recordings,
    e.g. a GelSight Mini's frames with the border its software cuts off; :func:`frame_crop` reads them)."""
    p.add_argument("--crop", type=float, nargs="+", default=[], metavar="SHARE",
                   help="shares cut off the frames' borders as they are read: one for every border or four (top, "
                        "bottom, left, right); 0.142857 for a GelSight Mini's raw frames (default: none)")
    p.add_argument("--size", type=int, nargs=2, default=[], metavar=("WIDTH", "HEIGHT"),
                   help="px the cut frames are resized to, e.g. 320 240 (default: as cut)")


def frame_crop(args: argparse.Namespace) -> FrameCrop | None:
    """The :class:`fv_algos.frame_crop.FrameCrop` of --crop / --size (None: neither given); SystemExit
    naming a bad value."""
    from fv_algos.frame_crop import FrameCrop
    try:
        return FrameCrop.from_lists(args.crop, args.size)
    except ValueError as error:
        raise SystemExit(f"--crop / --size: {error}") from None


def online_flags(p: argparse.ArgumentParser) -> None:
    """--online, --alarm and --plot: a trial-level model run frame by frame (`fv real cv`,
    `fv eval --trials`; :func:`check_online` refuses them where they do not apply)."""
    p.add_argument("--online", action="store_true",
                   help="trial-level models: also run the model frame by frame over every grasp, one camera at a "
                        "time (what the pipeline publishes on /slip; in `fv real cv` each fold's held-out network), "
                        "and report how early P(slip) tells slips from held grasps (`fv real cv --out` then also "
                        "holds every camera's running P(slip))")
    p.add_argument("--alarm", type=_alarm_rule, action="append", default=None, metavar="P[:FROM[:ROW]]",
                   help="--online: an alarm rule, raised when P(slip) >= P for ROW frames in a row from frame "
                        "FROM on (frames judged, at the model's frame rate; repeat the flag for several; default a "
                        "set from 0.5:0:1 to 0.99:100:10)")
    p.add_argument("--plot", type=output_with_suffix(".png"), default=None,
                   help="--online: PNG of the share of held and slip cameras at P(slip) >= 0.5 over time")


def check_online(args: argparse.Namespace, trial_level: bool) -> None:
    """ValueError naming the flags when --alarm or --plot come without --online, or --online with a
    model that has no running P(slip) (not ``trial_level``)."""
    given = [f for f, v in (("--alarm", args.alarm), ("--plot", args.plot)) if v is not None]
    if given and not args.online:
        raise ValueError(f"{' and '.join(given)} {'needs' if len(given) == 1 else 'need'} --online")
    if args.online and not trial_level:
        raise ValueError(f"--online needs a trial-level model (a window model has no running P(slip))")


def _alarm_rule(text: str):
    """An :class:`fv_algos.grasp_alarm.AlarmRule` from ``P[:FROM[:ROW]]`` (argparse type)."""
    from fv_algos.grasp_alarm import AlarmRule
    try:
        return AlarmRule.parse(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _data_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trials", type=Path, required=True, help="folder with labels.csv and the trial folders")
    crop_flags(p)
    p.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help=f"field cache folder (default {DEFAULT_CACHE})")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="processes for the fields, the contact motion and the folds of `cv` (default 1)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def _fit_args(p: argparse.ArgumentParser, window_steps: int) -> None:
    p.set_defaults(window_steps=window_steps)
    p.add_argument("--method", choices=("trial", "windows"), default="trial",
                   help="trial: trial-level temporal network on per-frame descriptors (default); "
                        "windows: window classifier (--arch)")
    p.add_argument("--arch", default="convlstm", help="windows: convlstm (the paper), cnn_lstm or lstm (default convlstm)")
    p.add_argument("--hidden", type=int, default=16, help="hidden channels / units (default 16)")
    p.add_argument("--layers", type=int, default=None,
                   help="trial: temporal convolutions (dilations 1, 2, 4, ...; default TrialNetConfig's)")
    p.add_argument("--members", type=int, default=None,
                   help="trial: networks in the ensemble, their logits averaged (default TrialNetConfig's)")
    p.add_argument("--stretch", type=float, default=None,
                   help="trial: training trials are resampled in time by a random factor in [1/S, S] "
                        "(1: never; default TrialNetConfig's)")
    p.add_argument("--clip", type=float, default=None,
                   help="trial: every descriptor is clamped to its [C, 1 - C] quantiles over the training frames "
                        "(0: their min and max; default TrialNetConfig's)")
    p.add_argument("--held-prefix", type=float, default=None,
                   help="trial: probability that a no-slip training trial is cut to its first 10 or more frames, "
                        "so the running P(slip) of a grasp in progress starts low (0: never; default "
                        "TrialNetConfig's)")
    p.add_argument("--start-swap", type=float, default=None,
                   help="trial: probability that a training camera's first 14 frames are traded for those of a "
                        "camera of the other label, so camera start-up bursts say nothing of the label (0: never; "
                        "default TrialNetConfig's)")
    p.add_argument("--fps", type=positive_float, default=None,
                   help="trial: the rate, Hz, the descriptors are taken at (faster videos' frames picked at it; "
                        "default: the rate most of the videos have)")
    p.add_argument("--reference-frame", type=int, default=None,
                   help="trial: the frame of each video taken as the skin at rest, where the descriptors start "
                        "(default TrialNetConfig's: the cameras' stale start-up frames come before it)")
    p.add_argument("--balance", default=None,
                   help="trial: how each training batch is drawn: half slip, half no slip, each half drawn alike "
                        "from every set-up with trials of its label (setup, the default: set-ups from the table's "
                        "setup column, else told apart by their marker pitch) or from all the trials of its label "
                        "(label)")
    p.add_argument("--steps", type=int, default=None,
                   help=f"optimizer steps (default: trial: TrialNetConfig's, windows: {window_steps})")
    p.add_argument("--batch-size", type=int, default=None, help="default: trial: TrialNetConfig's, windows: 32")
    p.add_argument("--lr", type=positive_float, default=None, help="default: trial: TrialNetConfig's, windows: 1e-3")
    p.add_argument("--seed", type=random_seed, default=0)
    p.add_argument("--init", default=None, help=f"fine-tune from this model (every fold's, in cv), a {model_help()}: "
                   "with --method trial a trial-level model, whose hidden, layers and members are used (the "
                   "descriptors' clamp range is taken from these trials); with windows a window model, whose "
                   "architecture is used; --steps counts the extra steps")
    p.add_argument("--stride", type=int, default=5, help="frames between window starts (default 5)")
    p.add_argument("--activity-px", type=float, default=None, help="activity (px/frame) from which a slip "
                   "trial's window is labelled slip (default: the TrialRule default)")
    p.add_argument("--top-k", type=int, default=None, help="windows averaged for the trial score")


def _rule(args: argparse.Namespace):
    from fv_algos.trial_eval import TrialRule
    overrides = {k: v for k, v in (("activity_px", args.activity_px), ("top_k", args.top_k)) if v is not None}
    return TrialRule(stride=args.stride, **overrides)


def _read_trials(args: argparse.Namespace) -> list[Trial]:
    """The trials of ``args.trials``, checked before any video is read against what needs the table alone: an
    `fv real train --cv-report` (its trials), an `fv real cv` deal (--folds against the objects; it was refused
    once every video's fields were computed). --crop / --size are checked before the table is read."""
    from fv_algos.real_trials import read_trials
    from fv_algos.trial_eval import object_folds
    frame_crop(args)  # a bad --crop / --size first: it needs no table
    trials = read_trials(args.trials)
    _check_cv_trials(getattr(args, "cv_report", None), trials)
    if getattr(args, "folds", None) is not None:
        object_folds([t.object for t in trials], args.folds, args.seed)
    return trials


def _load(args: argparse.Namespace, reference_frame: int = 1, trials: list[Trial] | None = None):
    """(trials, fields, seconds) of the trials in ``args.trials`` (``trials``: those, read already) from
    ``reference_frame`` of each video on, the frames cut by --crop / --size, fields cached under ``args.cache``
    (None: no cache) and computed in ``args.workers`` processes."""
    from fv_algos.real_trials import trial_fields
    crop = frame_crop(args)
    trials = _read_trials(args) if trials is None else trials
    started = time.perf_counter()
    fields = trial_fields(trials, args.cache, workers=args.workers, reference_frame=reference_frame, crop=crop,
                          progress=not args.no_progress)
    return trials, fields, time.perf_counter() - started


def _fields(args: argparse.Namespace) -> int:
    from fv_algos.real_trials import tracking_quality
    trials, fields, seconds = _load(args)
    quality = tracking_quality(fields)
    report = {"trials": len(trials), "wall_s": seconds, "cache": str(args.cache), **quality}
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f"{len(trials)} trials, {quality['videos']} videos, {quality['frames']} frames in {seconds:.1f} s; "
              f"markers valid per frame: mean {quality['valid_share_mean']:.3f}, min {quality['valid_share_min']:.3f}; "
              f"frames with a swap flagged: {quality['frames_with_swaps']}; cache {args.cache}")
        for video, missing in quality["short_videos"].items():
            print(f"  {video}: the last {missing} frames listed could not be decoded")
    return 0


def _fit_config(args: argparse.Namespace):
    import torch
    from fv_algos.trial_eval import fit_config
    torch.set_num_threads(1)
    return fit_config(args.arch, args.hidden, _given(args.steps, args.window_steps), _given(args.batch_size, 32),
                      _given(args.lr, 1e-3), args.seed, _rule(args))


def _given(value, default):
    """``value`` unless it was not given (None)."""
    return default if value is None else value


def _window_init(args: argparse.Namespace) -> str | None:
    """The path of the window model `--init` names (a shipped name or a path), None without."""
    from nodes.shipped_models import model_path
    return None if args.init is None else str(model_path(args.init))


def _trial_config(args: argparse.Namespace):
    """The trial network's training config of `args`, and the network `--init` names (None without): its hidden,
    layers and members replace those of `args`. ValueError when it is no trial-level model."""
    import torch
    from fv_algos.trial_net import TrialNetConfig, load_trial_model
    from nodes.shipped_models import model_path
    torch.set_num_threads(1)
    default = TrialNetConfig()
    config = TrialNetConfig(hidden=args.hidden, layers=_given(args.layers, default.layers),
                            members=_given(args.members, default.members),
                            stretch=_given(args.stretch, default.stretch), clip=_given(args.clip, default.clip),
                            held_prefix=_given(args.held_prefix, default.held_prefix),
                            start_swap=_given(args.start_swap, default.start_swap),
                            balance=_given(args.balance, default.balance),
                            reference_frame=_given(args.reference_frame, default.reference_frame),
                            steps=_given(args.steps, default.steps),
                            batch=_given(args.batch_size, default.batch), lr=_given(args.lr, default.lr),
                            seed=args.seed)
    if args.init is None:
        return config, None
    init = load_trial_model(model_path(args.init)).net
    return replace(config, hidden=init.hidden, layers=init.layers, members=init.members), init


def _trial_inputs(args: argparse.Namespace, reference_frame: int, params: ContactMotionParams | None = None,
                  fps: float | None = None, stretch: float = 1.0):
    """(trials, fields, field seconds, per-trial descriptor inputs, labels (n_trials,), their frame rate) of
    ``args.trials``, fields and contact series (``params``, None: the defaults) from ``reference_frame`` of each
    video on, cached under ``args.cache`` (None: no cache), in ``args.workers`` processes. The descriptors are
    taken at ``fps`` Hz (None: the rate most videos have), the frames of faster videos picked at it; slower
    videos are refused beyond ``stretch`` (:func:`fv_algos.frame_rate.judged_rates`). The fields returned are
    all the frames' (for the tracking quality)."""
    import numpy as np
    from fv_algos.contact_motion import ContactMotionParams, trial_series
    from fv_algos.frame_rate import judged_rates, picked_frames
    from fv_algos.trial_net import trial_inputs
    trials = _read_trials(args)
    fps, faster = judged_rates(trials, fps, stretch)  # (from the table and the containers: before the fields)
    trials, fields, field_s = _load(args, reference_frame, trials)
    paths = {(t.name, camera): path for t in trials for camera, path in t.videos.items()}
    series = trial_series(trials, args.cache, reference_frame, params or ContactMotionParams(), workers=args.workers,
                          rates={paths[key]: (rate, fps) for key, rate in faster.items()}, crop=frame_crop(args),
                          progress=not args.no_progress)
    picked = {key: value if key not in faster else value.at(picked_frames(len(value.fields), faster[key], fps))
              for key, value in fields.items()}
    inputs = trial_inputs(trials, series, picked)
    return trials, fields, field_s, inputs, np.array([t.label for t in trials]), fps


def _setups(args: argparse.Namespace, trials: Sequence[Trial], config) -> list[str] | None:
    """Each trial's set-up (:func:`fv_algos.setups.trial_setups`) when the trial network's ``config`` balances
    batches over them, else None."""
    from fv_algos.setups import trial_setups
    return trial_setups(trials, config.reference_frame, frame_crop(args)) if config.balance == "setup" else None


def _setup_record(setups: Sequence[str] | None, labels) -> dict[str, dict[str, int]] | None:
    """Trials per set-up and label, for a report (None without set-ups)."""
    from fv_algos.setups import setup_counts
    return None if setups is None else setup_counts(setups, labels)


def _cv(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    check_online(args, args.method == "trial")
    if args.method == "trial":
        from fv_algos.trial_net import cross_validate_trials
        config, init = _trial_config(args)
        trials, _, _, inputs, labels, fps = _trial_inputs(args, config.reference_frame, fps=args.fps,
                                                          stretch=config.stretch)
        config = replace(config, fps=fps)
        setups = _setups(args, trials, config)
        report = cross_validate_trials(inputs, labels, [t.object for t in trials], args.folds, args.seed, config,
                                       args.workers, progress=not args.no_progress, online=args.online, init=init,
                                       setups=setups)
        report["config"] = {"method": "trial", **asdict(config), "folds": args.folds, "init": args.init}
        report["setups"] = _setup_record(setups, labels)
        if args.online:
            report["online"] = _online_report(report["running"], labels, args, fps)
    else:
        from fv_algos.trial_eval import cross_validate, trial_windows
        config = _fit_config(args)
        trials, fields, _ = _load(args)
        data = trial_windows(trials, fields, config.train.model.window, config.rule)
        report = cross_validate(data, config, args.folds, args.seed, _window_init(args), progress=not args.no_progress,
                                workers=args.workers)
    report["wall_s"] = time.perf_counter() - started
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=1))
    report.pop("running", None)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        for r in report["folds"]:
            window = f"window acc {_figure(r['window_accuracy'])}  " if "window_accuracy" in r else ""
            print(f"fold {r['fold']}: trials {r['n_trials']:3d}  {window}"
                  f"trial acc {r['trial_accuracy']:.3f}  objects {', '.join(r['objects'])}")
        s = report["summary"]
        window = (f"; window accuracy {_figure(s['window_accuracy_mean'])} +/- {_figure(s['window_accuracy_std'])}"
                  if "window_accuracy_mean" in s else "")
        print(f"object-held-out trial accuracy {s['trial_accuracy_mean']:.3f} +/- {s['trial_accuracy_std']:.3f} "
              f"(worst fold {s['worst_fold']}: {s['trial_accuracy_min']:.3f}; pooled {s['pooled_trial_accuracy']:.3f})"
              f"{window}")
        if args.online:
            _print_online(report["online"])
    return 0


def _online_report(running: list, labels, args: argparse.Namespace, fps: float) -> dict[str, object]:
    """:func:`fv_algos.grasp_alarm.online_summary` of ``running`` (per trial, per camera: P(slip) after
    every frame judged, ``fps`` Hz), with ``args.alarm`` rules (None: the defaults); the ``args.plot`` PNG
    when given."""
    from fv_algos.grasp_alarm import DEFAULT_RULES, above_curves, online_summary
    summary = online_summary(running, labels, fps, rules=args.alarm or DEFAULT_RULES)
    if args.plot is not None:
        from nodes.plots import curve_plot
        held, slips = above_curves(running, labels)
        seconds = [t / fps for t in range(held.size)]
        curve_plot({"held grasps' cameras": (seconds, held * 100), "slips' cameras": (seconds, slips * 100)},
                   args.plot, title="running P(slip), frame by frame: cameras at P(slip) >= 0.5",
                   x_label="time after the reference frame (s)", y_label="% of the cameras still recording")
        summary["plot"] = str(args.plot)
    return summary


def _print_online(online: dict) -> None:
    """The online part of an `fv real cv --online` or `fv eval --trials --online` report as text."""
    def pct(share) -> str:
        return "-" if share is None else f"{100 * share:.0f}%"
    cameras = online["cameras"]
    print(f"running P(slip), {cameras['held']} held and {cameras['slip']} slip cameras; one camera right at the "
          f"end of its grasp: {pct(online['camera_end_accuracy'])}")
    for row in online["at"]:
        print(f"  at {row['seconds']:g} s: P >= 0.5 for {pct(row['held_above'])} of {row['held_recording']} held, "
              f"{pct(row['slip_above'])} of {row['slip_recording']} slip cameras")
    for row in online["alarms"]:
        first = "-" if row["slip_median_first_s"] is None else f"{row['slip_median_first_s']:.1f} s"
        print(f"  alarm {row['rule']}: {pct(row['held_alarmed'])} of held, {pct(row['slip_alarmed'])} of slip "
              f"cameras; slips' median first alarm {first}")
    if "plot" in online:
        print(f"  plot: {online['plot']}")


def _train(args: argparse.Namespace) -> int:
    if args.method == "trial":
        return _train_trial(args)
    import numpy as np
    from fv_algos.slip.classifier import Checkpoint, save_checkpoint
    from fv_algos.slip.models import count_parameters
    from fv_algos.trial_eval import fit, fit_record, fit_train_config, trial_windows
    config = _fit_config(args)
    init = _window_init(args)
    _check_cv_report(args.cv_report, "windows", fit_record(config, init))
    trials, fields, _ = _load(args)
    data = trial_windows(trials, fields, config.train.model.window, config.rule)
    started = time.perf_counter()
    model, threshold, record = fit(data, np.arange(len(trials)), config, init=init)
    checkpoint = Checkpoint(fit_train_config(config, init).model, model.state_dict(), record["steps"], None, config.train.to_dict(), [])
    path = save_checkpoint(args.out, checkpoint)
    info = {
        "model": path.stem.removeprefix("slip_"),
        "trained_on": {"trials_dir": str(args.trials), "trials": len(trials),
                       "slip": int(sum(t.label for t in trials)), "objects": len({t.object for t in trials})},
        "fit": {"train": config.train.to_dict(), "rule": asdict(config.rule), "init": init,
                "seconds": time.perf_counter() - started},
        "trial_threshold": threshold,
        "training": record,
        "parameters": count_parameters(model),
        "command": " ".join(["fv", *sys.argv[1:]]),
    }
    _write_sidecar(path, info, args.cv_report)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KiB, {info['parameters']} parameters, "
          f"trial threshold {threshold:.3f}) and {path.with_suffix('.json')}")
    return 0


def _cv_report(text: str) -> dict:
    """An `fv real cv --out` report, read before any training (argparse type): a file that is not
    one is named now, not after the model is written without its record."""
    try:
        report = json.loads(Path(text).read_text())
    except (OSError, ValueError) as exc:
        raise argparse.ArgumentTypeError(f"{text}: not an `fv real cv --out` report ({exc})") from None
    if not isinstance(report, dict) or "summary" not in report:
        raise argparse.ArgumentTypeError(f"{text}: not an `fv real cv --out` report (no summary)")
    return report


def _check_cv_report(report: dict | None, method: str, config: dict, later: tuple[str, ...] = ()) -> None:
    """ValueError naming what differs when ``report`` (an `fv real cv --out` report to record beside a model, None:
    none) cross-validated another method (``method``: "trial" or "windows") or networks trained otherwise than by
    ``config`` (the training's config record, nested records compared key by key; the deal's seed and folds, and
    whether a progress bar was drawn, may differ): its figures would be recorded as this model's. Checked before
    the training, so that nothing is trained for a record refused after; ``later``: keys not known yet (the frame
    rate, read from the videos), checked by a second call with those alone once they are."""
    if report is None:
        return
    made = report.get("config", {})
    made_method = made.get("method", "windows")  # window reports name no method
    if made_method != method:
        raise ValueError(f"--cv-report: the report cross-validated the {made_method} model, this trains the {method} one")
    differ = _differences(made, json.loads(json.dumps(config)), ("seed", "folds", "progress", *later))  # tuples as lists
    if differ:
        raise ValueError(f"--cv-report: the report's networks were trained otherwise: {'; '.join(differ)}")


def _check_cv_trials(report: dict | None, trials: list[Trial]) -> None:
    """ValueError when ``report`` (an `fv real cv --out` report to record beside a model; None: none) cross-validated
    other trials than ``trials``, the training's: its folds' objects and trial count must be theirs (another set's
    figures were recorded as this model's). Checked once the table is read, before any video is."""
    if report is None:
        return
    folds = report.get("folds", [])
    theirs, mine = {o for fold in folds for o in fold["objects"]}, {t.object for t in trials}
    count = sum(len(fold["trials"]) for fold in folds)
    if theirs != mine or count != len(trials):
        only = "; ".join(f"objects only {where}: {', '.join(sorted(names)[:5])}" + (" ..." if len(names) > 5 else "")
                         for where, names in (("there", theirs - mine), ("here", mine - theirs)) if names)
        raise ValueError(f"--cv-report: the report cross-validated other trials: {count} trials of {len(theirs)} "
                         f"objects (this training: {len(trials)} of {len(mine)})" + (f"; {only}" if only else ""))


def _differences(made: dict, config: dict, ignore: tuple[str, ...], prefix: str = "") -> list[str]:
    """'key value (this training: value)' for every key of ``config`` that ``made`` holds with another value, keys
    of nested dicts as 'outer.key'; keys in ``ignore`` are left out at every level."""
    differ = []
    for key, value in config.items():
        if key in ignore or key not in made or made[key] == value:
            continue
        if isinstance(value, dict) and isinstance(made[key], dict):
            differ += _differences(made[key], value, ignore, f"{prefix}{key}.")
        else:
            differ.append(f"{prefix}{key} {made[key]!r} (this training: {value!r})")
    return differ


def _write_sidecar(path: Path, info: dict, cv_report: dict | None) -> None:
    """Write `info` (plus the summary of an `fv real cv --out` report, and its online part when it
    was run with --online) beside the model as JSON."""
    if cv_report is not None:
        info["cross_validation"] = cv_report["summary"]
        if "online" in cv_report:
            info["cross_validation_online"] = {k: v for k, v in cv_report["online"].items() if k != "plot"}
    path.with_suffix(".json").write_text(json.dumps(info, indent=1))


def _train_trial(args: argparse.Namespace) -> int:
    from fv_algos.slip.models import count_parameters
    from fv_algos.trial_net import DESCRIPTORS, fit_trial_net, judge_trials, save_trial_model, trial_probability
    started = time.perf_counter()
    config, init = _trial_config(args)
    _check_cv_report(args.cv_report, "trial", {**asdict(config), "init": args.init}, later=("fps",))
    trials, _, _, inputs, labels, fps = _trial_inputs(args, config.reference_frame, fps=args.fps,
                                                      stretch=config.stretch)
    config = replace(config, fps=fps)
    _check_cv_report(args.cv_report, "trial", {"fps": fps})
    setups = _setups(args, trials, config)
    net = fit_trial_net(inputs, labels, config, init, setups)
    path = save_trial_model(args.out, net, config)
    info = {
        "model": path.stem.removeprefix("slip_"),
        "kind": "trial-level temporal network on per-frame contact-motion and field descriptors (fv_algos.trial_net)",
        "trained_on": {"trials_dir": str(args.trials), "trials": len(trials), "slip": int(labels.sum()),
                       "objects": len({t.object for t in trials})},
        "config": asdict(config), "setups": _setup_record(setups, labels), "init": args.init,
        "parameters": count_parameters(net),
        "descriptors": list(DESCRIPTORS),
        "decision": "slip when p >= 0.5",
        "training_trial_accuracy": judge_trials(trial_probability(net, inputs), labels)["trial_accuracy"],
        "seconds": time.perf_counter() - started,
        "command": " ".join(["fv", *sys.argv[1:]]),
    }
    _write_sidecar(path, info, args.cv_report)
    print(f"wrote {path} and {path.with_suffix('.json')} (training trial accuracy "
          f"{info['training_trial_accuracy']:.3f})")
    return 0


def _eval_trial_net(args: argparse.Namespace, model: TrialModel) -> dict[str, object]:
    """Report of the trial-level ``model`` on ``args.trials`` (video to decision, from the model's
    reference frame of each video on)."""
    from fv_algos.trial_net import judge_trials, running_probabilities, trial_probability
    trials, fields, field_s, inputs, labels, _ = _trial_inputs(args, model.reference_frame, model.params, model.fps,
                                                               model.stretch)
    report = judge_trials(trial_probability(model.net, inputs), labels)
    online = {}
    if args.online:
        running = running_probabilities(model.net, inputs, args.workers)
        online["online"] = _online_report(running, labels, args, model.fps)
    return {"trial_accuracy": report["trial_accuracy"], "n_trials": report["n_trials"], "window_accuracy": None,
            "n_windows": 0, "confusion": report["confusion"], "trial_f1": report["trial_f1"], "threshold": 0.5,
            "method": "trial (trial-level: no windows, window_accuracy is null)", "model_fps": model.fps,
            "frames_judged": sum(x.shape[1] for cameras in inputs for x in cameras),
            **_path_report(trials, fields, field_s, report["probability"], 0.5), **online}


def _path_report(trials: Sequence[Trial], fields: TrialFields, field_s: float, scores: Sequence[float],
                 threshold: float) -> dict[str, object]:
    """What both kinds of model report of the video-to-decision path: the fields' seconds and frames,
    the tracking quality, and per trial its name, object, label ('slip' / 'no_slip'), slip score (p
    or window score), decision (score >= ``threshold``) and whether it is right."""
    from fv_algos.real_trials import tracking_quality
    decisions = []
    for t, score in zip(trials, scores):
        slip = bool(score >= threshold)
        decisions.append({"trial": t.name, "object": t.object, "label": ("no_slip", "slip")[t.label],
                          "score": float(score), "slip": slip, "correct": slip == bool(t.label)})
    return {"fields_s": field_s, "frames": int(sum(v.fields.shape[0] for v in fields.values())),
            "tracking": tracking_quality(fields), "trials": decisions}


def eval_trials_command(args: argparse.Namespace) -> int:
    """Judge a slip model on a folder of real trials, the whole way from video to decision.

    Needs args.model (shipped name or checkpoint), args.trials (folder), args.json; optional
    args.cache (None: fields are computed, not cached), args.workers and the :func:`online_flags`
    (--online for a trial-level model: its running P(slip) over every camera). The window stride, top-k
    and trial threshold come from the model's JSON sidecar (`slip_<name>.json`) when it has them,
    else the TrialRule defaults and threshold 0.5. Prints trial_accuracy, n_trials,
    window_accuracy, confusion ([[TN, FP], [FN, TP]] at trial level), the timing (frames judged
    included), tracking quality and each trial's score and decision (without --json: the misjudged
    trials).
    A trial-level model (`gelsight` is one: :func:`nodes.shipped_models.model_path`) has no windows: its window_accuracy is null; it
    judges every video at the model's frame rate (a faster video's frames picked at it, a video too slow
    for it refused by name: :mod:`fv_algos.frame_rate`)."""
    import cv2
    import torch
    from fv_algos.trial_net import read_trial_model
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    started = time.perf_counter()
    from nodes.shipped_models import model_path
    path = model_path(args.model)
    trial_model = read_trial_model(path)
    check_online(args, trial_model is not None)
    out = _eval_windows(args, path) if trial_model is None else _eval_trial_net(args, trial_model)
    wall = time.perf_counter() - started
    out = {"model": str(path), **out, "wall_s": wall, "s_per_trial": wall / out["n_trials"],
           "ms_per_frame": 1e3 * wall / out["frames"]}
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        window = _figure(out["window_accuracy"])
        print(f"{out['n_trials']} trials: trial accuracy {out['trial_accuracy']:.3f}, window accuracy "
              f"{window}, confusion {out['confusion']} ({wall:.0f} s, {out['s_per_trial']:.2f} s/trial)")
        for t in out["trials"]:
            if not t["correct"]:
                print(f"  wrong: {t['trial']} ({t['object']}): {t['label']}, score {t['score']:.2f}")
        if "online" in out:
            _print_online(out["online"])
    return 0


def _figure(value: float | None) -> str:
    """A figure of a report to 3 decimals, "n/a" for None (a trial model's window accuracy, or no window labelled)."""
    return "n/a" if value is None else f"{value:.3f}"


def _eval_windows(args: argparse.Namespace, path: Path) -> dict[str, object]:
    """Report of the window classifier checkpoint at ``path`` on ``args.trials`` (video to decision)."""
    import numpy as np
    from fv_algos.slip.classifier import SlipClassifier
    from fv_algos.trial_eval import TrialRule, judge, trial_windows
    sidecar = path.with_suffix(".json")
    info = json.loads(sidecar.read_text()) if sidecar.is_file() else {}
    if not info:  # (a checkpoint copied without it was judged with another threshold, without a word)
        log.warning("no %s beside %s: judged with trial threshold 0.5 and the default window rule (a trained "
                    "model's own are in that file, which fv real train writes beside it)", sidecar.name, path)
    rule = TrialRule(**info["fit"]["rule"]) if "fit" in info else TrialRule()
    threshold = float(info.get("trial_threshold", 0.5))
    classifier = SlipClassifier(path, threads=1)
    trials, fields, field_s = _load(args)
    data = trial_windows(trials, fields, classifier.config.window, rule)
    report = judge(classifier.model, data, np.arange(len(trials)), threshold, rule.top_k)
    return {"trial_accuracy": report["trial_accuracy"], "n_trials": report["n_trials"],
            "window_accuracy": report["window_accuracy"], "n_windows": report["n_windows"],
            "confusion": report["confusion"], "trial_f1": report["trial_f1"], "threshold": threshold,
            "rule": asdict(rule), "method": "windows",
            **_path_report(trials, fields, field_s, report["scores"], threshold)}
