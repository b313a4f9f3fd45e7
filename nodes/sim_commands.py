"""`fv sim` (write or preview a simulated sequence) and `fv calibrate` (fisheye
chessboard calibration)."""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from nodes.arg_types import output_file, output_folder, output_with_suffix, positive_float, positive_int, random_seed

if TYPE_CHECKING:
    from fv_algos.sim.scene import Scene


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="render a simulated sequence with ground truth, or a preview picture")
    p.add_argument("--scene", default="", help="scene file (YAML/JSON); default: random scenarios")
    p.add_argument("--out", type=output_folder, help="folder for PNG frames, previews and truth.npz/json")
    p.add_argument("--frames", type=int, default=60, help="frames to write (default 60)")
    p.add_argument("--preview", type=output_with_suffix(".png"), help="write one preview PNG (frame, true markers, true field)")
    p.add_argument("--frame", type=int, default=-1, help="which frame to preview (default: the last of --frames)")
    p.add_argument("--seed", type=random_seed, default=0)
    p.set_defaults(func=_sim)

    p = sub.add_parser("calibrate", help="fisheye chessboard calibration from images or a video")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", type=Path, help="folder of chessboard images")
    src.add_argument("--video", type=Path, help="video of a chessboard")
    p.add_argument("--every", type=positive_int, help=f"--video only: use every k-th frame (default {DEFAULT_EVERY})")
    p.add_argument("--board", default="7x5",
                   help="INNER corners COLSxROWS, one less than the squares each way (default 7x5: 8x6 squares)")
    p.add_argument("--square-mm", type=float, default=2.5, help="square side in mm (default 2.5)")
    p.add_argument("--max-rms-px", type=positive_float, default=2.0,
                   help="refuse a calibration whose reprojection RMS is over this (px, default 2); a view over it "
                        "and 3x the median view is dropped first")
    p.add_argument("--out", type=output_file, required=True, help="calibration JSON the camera node loads")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_calibrate)


def _sim(args: argparse.Namespace) -> int:
    from fv_algos.sim.scene import load_scene
    if args.out is None and args.preview is None:
        raise ValueError("give --out DIR and/or --preview FILE.png")
    if args.frames < 1:
        raise ValueError(f"--frames {args.frames} must be >= 1")
    if args.frame < -1:
        raise ValueError(f"--frame {args.frame} must be >= 0 (or -1: the last of --frames)")
    if args.out is not None and args.out.is_dir() and any(args.out.iterdir()):
        raise ValueError(f"--out {args.out} holds files already: an earlier sequence's frames would stay among "
                         "these; choose an empty or new folder")
    scene = load_scene(args.scene) if args.scene else None
    frames = args.frames if scene is None else min(args.frames, scene.n_frames)
    index = args.frame if args.frame >= 0 else frames - 1
    if scene is not None and index >= scene.n_frames:
        raise ValueError(f"--frame {index}: the scene has {scene.n_frames} frames (0 to {scene.n_frames - 1})")
    try:
        return _simulate(args, scene, frames, index)
    except ValueError as exc:
        if scene is None:
            raise
        raise ValueError(f"{args.scene}: {exc}") from None  # a frame the scene's mechanics cannot play


def _simulate(args: argparse.Namespace, scene: Scene | None, frames: int, index: int) -> int:
    """`fv sim`'s writing, once its arguments and scene are checked: ``frames`` frames to --out, frame
    ``index`` to --preview. ValueError for a frame the mechanics cannot play, naming it."""
    from fv_algos.atomic_file import write_image
    from fv_algos.sim.sensor import SimSensor, preview_image, write_sequence
    if args.out is not None:
        written = write_sequence(SimSensor(scene, seed=args.seed), args.out, frames)
        whole = f" (the whole scene; --frames asked for {args.frames})" if written < args.frames else ""
        print(f"wrote {written} frame{'' if written == 1 else 's'} with ground truth to {args.out}{whole}")
    if args.preview is not None:
        args.preview.parent.mkdir(parents=True, exist_ok=True)
        if args.out is not None and index < frames:  # written already: no second simulation
            shutil.copyfile(args.out / f"preview_{index:05d}.png", args.preview)
            truth = json.loads((args.out / "truth.json").read_text())["frames"][index]
            state, area = truth["slip_state"], truth["contact_area_mm2"]
        else:
            frame = next(SimSensor(scene, seed=args.seed).frames(index))  # frames before it: mechanics only
            write_image(args.preview, preview_image(frame))
            state, area = frame.truth.slip_state, frame.truth.contact_area_mm2
        print(f"wrote preview of frame {index} to {args.preview} (slip state {state}, contact {area:.1f} mm^2)")
    return 0


DEFAULT_EVERY = 10  # `fv calibrate --video`: every k-th frame by default
WORST_VIEWS_SHOWN = 3  # views named in the text report, worst RMS first


def _calibration_views(args: argparse.Namespace) -> list[tuple[str, object]]:
    """The (name, (H, W) uint8 image) views of --images, or of every --every-th frame of --video."""
    from fv_algos.calibration import CalibrationParams, load_images, load_video_frames
    if args.images is not None:
        if args.every is not None:
            raise ValueError("--every applies to --video only: --images uses every image of the folder")
        return load_images(args.images)
    every = DEFAULT_EVERY if args.every is None else args.every
    views = load_video_frames(args.video, every)
    needed = CalibrationParams().min_views
    if len(views) < needed:  # else it failed as boards not found, with the board size as the hint
        frames = len(views) if every == 1 else len(load_video_frames(args.video, 1))  # a short video: read again
        if frames < needed:
            raise ValueError(f"{args.video} holds {frames} frame(s), fewer than the {needed} views a calibration "
                             "needs: film the board in more positions")
        raise ValueError(f"--every {every} took {len(views)} frame(s) of {args.video}, fewer than the {needed} views "
                         f"a calibration needs: give --every at most {frames // needed} (the video holds {frames})")
    return views


def _calibrate(args: argparse.Namespace) -> int:
    from fv_algos.calibration import CalibrationParams, Chessboard, calibrate_fisheye
    cols, _, rows = args.board.partition("x")
    if not (cols.isdigit() and rows.isdigit()):
        raise ValueError(f"--board {args.board!r} is not COLSxROWS, e.g. 7x5")
    board = Chessboard((int(cols), int(rows)), args.square_mm)
    result = calibrate_fisheye(_calibration_views(args), CalibrationParams(board=board, max_rms_px=args.max_rms_px))
    result.camera.save(args.out)
    per_view = dict(zip(result.used, result.per_view_rms_px.tolist()))
    report = {"rms_px": result.rms_px, "used": len(result.used), "rejected": result.rejected,
              "per_view_rms_px": per_view, "K": result.camera.K.tolist(), "D": result.camera.D.tolist(),
              "out": str(args.out)}
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        for name, why in result.rejected.items():
            print(f"rejected {name}: {why}")
        worst = sorted(per_view.items(), key=lambda item: -item[1])[:WORST_VIEWS_SHOWN]
        print("worst views: " + ", ".join(f"{name} {rms:.3f} px" for name, rms in worst))
        print(f"calibrated from {len(result.used)} views, RMS {result.rms_px:.3f} px -> {args.out}")
    return 0
