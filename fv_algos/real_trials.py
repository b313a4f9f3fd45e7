"""Real grasp trials (e.g. GelSight Mini recordings) -> displacement fields and tracking quality.

A trial folder holds one video per finger camera (``camera_0.avi``, optionally ``camera_2.avi``; or
``.mp4``, ``.mkv``, ``.mov``, ``.m4v``)
and one label for the whole trial. A trial table is ``labels.csv`` in the dataset root with at
least the columns ``trial`` (folder relative to the root), ``object`` and ``label`` (``slip`` /
``no_slip``, or 1 / 0); any other columns are kept as ``Trial.extra``.

Each video goes through :class:`fv_algos.perception.Perception` frame by frame: the frame
``reference_frame`` (default 1, frame 0 of these cameras is often stale) is the undeformed skin,
earlier frames are dropped. Only markers the tracker marks valid (measured and consistent with
their neighbours this frame) feed the field, so markers that leave the view or blur do not
poison it. Per frame we also keep the share of reference markers valid and the number of
identity swaps / wrong matches detected: markers the tracker dropped as swaps (``TrackState.swapped``)
plus valid markers :func:`fv_algos.tracking.neighbour_consistency` flags.

Window labels and trial decisions live in :mod:`fv_algos.trial_eval`: a window of a slip trial
takes the slip label only when the field is moving (its activity reaches a threshold), since a
slip trial also holds its grasp and lift before the slip; every window of a no-slip trial is a
no-slip example; a trial's decision pools the window probabilities of both cameras.
"""
from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
import os
import sys
import time
import zipfile
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np
from tqdm import tqdm

from fv_algos import detection, frame_crop, perception, reference_markers, tracking
from fv_algos import field as field_module
from fv_algos.atomic_file import write_atomically
from fv_algos.frame_crop import FrameCrop
from fv_algos.perception import Perception, PerceptionParams
from fv_algos.slip.windows import FLOAT16_MAX
from fv_algos.text_file import read_utf8
from fv_algos.tracking import TrackState, neighbour_consistency

T = TypeVar("T")
log = logging.getLogger(__name__)

LABELS_FILE = "labels.csv"
CAMERAS = ("camera_0", "camera_2")
VIDEO_SUFFIXES = (".avi", ".mp4", ".mkv", ".mov", ".m4v")  # a camera's video: camera_0.avi, ...
LABEL_VALUES = {"no_slip": 0, "slip": 1, "0": 0, "1": 1}
REQUIRED_COLUMNS = ("trial", "object", "label")
CACHE_VERSION = 3
# the frame width (px) real-trial fields are read at by the models, whatever the camera's: the GelSight Mini's 320x240
FIELD_WIDTH_PX = 320
# the grid (rows, columns) of the fields `video_fields` gives (the default FieldParams'), which the models trained on
# real trials read: their divergence and curl are per grid cell
FIELD_GRID = field_module.FieldParams().grid_shape


@dataclass(frozen=True)
class Trial:
    """One labelled grasp.

    name: folder relative to the dataset root (e.g. "train/blue_mug/exp_num_4").
    folder: absolute folder. label: 0 no slip, 1 slip. videos: camera name -> video path, for the
    cameras present (camera_0 always). extra: the table's other columns, as strings. row: where the
    table lists it ("DIR/labels.csv line 7"; empty for a trial made in code), for errors in its cells.
    """

    name: str
    object: str
    label: int
    folder: Path
    videos: dict[str, Path]
    extra: dict[str, str] = field(default_factory=dict)
    row: str = ""


def read_trials(root: str | Path) -> list[Trial]:
    """Trials listed in ``root/labels.csv`` (UTF-8, with or without the byte-order mark spreadsheets
    write), in file order. Header cells are read trimmed and in lower case (" Label" is "label"), rows
    of empty cells are skipped, and a trial's name is normalised (``./t1/`` is ``t1``).

    Raises FileNotFoundError naming the missing ``labels.csv`` or ``camera_0`` video, ValueError
    naming the file (and the line) for text that is not UTF-8, a missing or doubled column, a row short of
    fields (or with more that are not empty), an empty object, an unknown label, a trial listed twice
    (two names of one folder) or a camera with two videos (``camera_0.avi`` and ``camera_0.mp4``) or a
    video that is not a readable file (a broken link).
    """
    root = Path(root)
    table = root / LABELS_FILE
    if not table.is_file():
        raise FileNotFoundError(f"trial table not found: {table} (needs columns {', '.join(REQUIRED_COLUMNS)})")
    lines = _table_rows(table)
    header = [name.strip().lower() for name in lines[0][1]] if lines else []  # as a spreadsheet may write it: " Label"
    named = [name for name in header if name]  # columns without a name (a spreadsheet's used range) are left out
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing or len(set(named)) < len(named):
        raise ValueError(f"{table}: missing columns {missing} (has {named})" if missing
                         else f"{table}: a column is named twice ({named})")
    trials, seen = [], {}
    for line, cells in lines[1:]:
        where = f"{table} line {line}"
        if not any(cell.strip() for cell in cells):
            continue  # an empty line, or the empty rows (,,) a spreadsheet leaves below its table
        if len(cells) < len(header) or any(cell.strip() for cell in cells[len(header):]):
            raise ValueError(f"{where}: {len(cells)} fields, the header has {len(header)}")
        row = {name: cell for name, cell in zip(header, cells) if name}
        name, label, obj = row["trial"].strip(), row["label"].strip().lower(), row["object"].strip()
        if label not in LABEL_VALUES:
            raise ValueError(f"{where}: label {row['label']!r} is not slip / no_slip (or 1 / 0)")
        if not name:
            raise ValueError(f"{where}: no trial")
        name = os.path.normpath(name)
        folder = root / name
        same = folder.resolve()  # t1, ./t1 and t1/ are one folder
        if same in seen:
            raise ValueError(f"{where}: trial {name!r} is listed twice (also on line {seen[same]})")
        if not obj:
            raise ValueError(f"{where}: trial {name!r} has no object (object-held-out folds need one)")
        seen[same] = line
        extra = {k: v for k, v in row.items() if k not in REQUIRED_COLUMNS}
        trials.append(Trial(name, obj, LABEL_VALUES[label], folder, _camera_videos(folder, where), extra, where))
    if not trials:
        raise ValueError(f"{table} lists no trials")
    return trials


def _table_rows(table: Path) -> list[tuple[int, list[str]]]:
    """(line, cells) of each row of the CSV file ``table``, with the line it starts on. ValueError naming the
    file and that line for a quote that is never closed: it swallowed the lines after it into one cell (the
    error named a later, well-formed line, or a long table ended in the csv module's "field larger than field
    limit")."""
    reader = csv.reader(io.StringIO(read_utf8(table, " (a spreadsheet's \"CSV UTF-8\")"), newline=""))
    rows, start = [], 1
    try:
        for cells in reader:
            if any("\n" in cell or "\r" in cell for cell in cells):  # no column of the table holds a line end
                raise csv.Error(f"a quoted cell runs on to line {reader.line_num}")
            rows.append((start, cells))
            start = reader.line_num + 1
    except csv.Error as exc:
        raise ValueError(f"{table} line {start}: {exc} (a quote never closed?)") from None
    return rows


def _camera_videos(folder: Path, where: str) -> dict[str, Path]:
    """Camera name -> video of a trial ``folder`` (``camera_0`` always): one file per camera, its name and any of
    ``VIDEO_SUFFIXES`` in any case (`camera_2.MP4` and `Camera_0.avi` were neither read nor warned of). FileNotFoundError
    without a ``camera_0`` video, ValueError for a camera with two; both start with ``where`` (the
    table's line)."""
    videos = {}
    entries = sorted(folder.iterdir()) if folder.is_dir() else []
    for camera in CAMERAS:
        named = [path for path in entries if path.stem.lower() == camera and path.suffix.lower() in VIDEO_SUFFIXES]
        broken = [path for path in named if (path.is_symlink() and not path.is_file()) or path.is_dir()]
        if broken:
            raise ValueError(f"{where}: {broken[0]} is not a video file (a broken link or a folder)")
        found = [path for path in named if path.is_file()]
        if len(found) > 1:
            raise ValueError(f"{where}: {len(found)} videos for {camera}, keep one: {', '.join(map(str, found))}")
        videos.update({camera: path for path in found})
    if CAMERAS[0] not in videos:
        raise FileNotFoundError(f"{where}: video not found: {folder / CAMERAS[0]}{{{','.join(VIDEO_SUFFIXES)}}}")
    stray = sorted(path.name for path in entries if path.stem.lower().startswith("camera_")
                   and path.suffix.lower() in VIDEO_SUFFIXES and path.stem.lower() not in CAMERAS)
    if stray:
        log.warning("%s: %s left out: the cameras read are %s (one video each)", where, ", ".join(stray),
                    " and ".join(CAMERAS))
    return videos


def at_reference_width(fields: np.ndarray, width_px: int) -> np.ndarray:
    """float32 copy of ``fields`` (..., 3) px (dx, dy, |d|) of frames ``width_px`` wide, in px of the
    frame resized to ``FIELD_WIDTH_PX`` wide: the scale the models trained on real trials read, so
    that one grasp filmed at another resolution gives them the same input."""
    return np.asarray(fields, np.float32) * np.float32(FIELD_WIDTH_PX / width_px)


@dataclass
class VideoFields:
    """Fields and tracking quality of one video, from the reference frame on (F frames).

    fields: (F, H, W, 3) float16 px (dx, dy, magnitude); frame 0 is the reference (zeros).
    field_valid: (F,) bool, enough valid markers for a field (an invalid field is all zeros).
    valid_share: (F,) float32, share of the reference markers valid in each frame.
    swaps: (F,) int32, swaps detected in each frame (:func:`detected_swaps`).
    n_markers: markers found in the reference frame. seconds: wall time of decode + perception.
    width_px: width of the video's frames, px (the scale the fields are measured at).
    missing_frames: frames the video's container lists after the last one decoded (a truncated or
    damaged file, whose grasp is judged on the frames decoded; 0 when none are, or the container
    lists no count).
    """

    fields: np.ndarray
    field_valid: np.ndarray
    valid_share: np.ndarray
    swaps: np.ndarray
    n_markers: int
    seconds: float
    width_px: int
    missing_frames: int = 0

    def quality(self) -> dict[str, float]:
        """Tracking quality summary: markers, frames, mean / min share valid, frames with a swap, swaps,
        invalid fields and frames listed but not decoded."""
        return {
            "markers": self.n_markers,
            "frames": int(self.fields.shape[0]),
            "valid_share_mean": float(self.valid_share.mean()),
            "valid_share_min": float(self.valid_share.min()),
            "frames_with_swaps": int(np.count_nonzero(self.swaps)),
            "swaps": int(self.swaps.sum()),
            "invalid_fields": int(np.count_nonzero(~self.field_valid)),
            "missing_frames": self.missing_frames,
        }

    def at(self, frames: np.ndarray) -> VideoFields:
        """These fields at ``frames`` (K,) (indices from the reference on) only; the same markers,
        seconds, width and missing frames."""
        return VideoFields(self.fields[frames], self.field_valid[frames], self.valid_share[frames], self.swaps[frames],
                           self.n_markers, self.seconds, self.width_px, self.missing_frames)


def read_frames(path: str | Path, crop: FrameCrop | None = None) -> Iterator[np.ndarray]:
    """BGR frames (H, W, 3) uint8 of a video file, cut and resized by ``crop`` when given (a raw
    recording's frames made the ones a model was trained on, e.g. a GelSight Mini's border cut off);
    FileNotFoundError / ValueError name the file (ValueError also a crop that leaves nothing)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"video not found: {path}")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise ValueError(f"OpenCV cannot decode video {path}")
    try:
        while True:
            ok, frame = capture.read()
            if not ok:
                return
            yield frame if crop is None else crop.apply(frame)
    finally:
        capture.release()


def frame_count(path: str | Path) -> int:
    """Frames in a video according to its container (0 when unknown)."""
    capture = cv2.VideoCapture(str(path))
    try:
        return max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
    finally:
        capture.release()


def detected_swaps(state: TrackState) -> int:
    """Identity swaps / wrong matches detected in one frame: markers the tracker dropped as swaps
    (``state.swapped``) plus valid markers that :func:`fv_algos.tracking.neighbour_consistency` flags."""
    flagged = neighbour_consistency(state.reference_px, state.current_px, state.valid)
    return int(np.count_nonzero(state.swapped) + np.count_nonzero(flagged))


def float16_px(fields: np.ndarray) -> np.ndarray:
    """``fields`` (any shape, px) as the cache stores them and the trial models were trained on: float16,
    clipped to its range (+-65504 px; beyond it float16 holds only inf, whose gradients are NaN)."""
    return np.clip(fields, -FLOAT16_MAX, FLOAT16_MAX).astype(np.float16)


def video_fields(
    path: str | Path, params: PerceptionParams | None = None, reference_frame: int = 1, crop: FrameCrop | None = None
) -> VideoFields:
    """Run the perception core over one video (see the module docstring), its frames cut by ``crop``
    when given (:func:`read_frames`); ValueError naming the file when it has no frame at
    ``reference_frame`` or its reference shows too few markers. Frames the container lists after the
    last one decoded are counted in ``missing_frames``."""
    started = time.perf_counter()
    core = Perception(params or PerceptionParams.preset("default"))
    fields, field_valid, shares, swaps = [], [], [], []
    for index, frame in enumerate(read_frames(path, crop)):
        if index < reference_frame:
            continue
        if index == reference_frame:
            try:
                core.reset(frame)
            except ValueError as exc:
                raise ValueError(f"{path}: reference frame {reference_frame}: {exc}") from exc
        state, dense = core.step(frame)
        fields.append(dense.field)
        field_valid.append(dense.valid)
        shares.append(state.valid.mean())
        swaps.append(detected_swaps(state))
    if not fields:
        raise ValueError(f"{path}: no frame at reference_frame={reference_frame}")
    return VideoFields(
        float16_px(np.stack(fields)),
        np.array(field_valid, dtype=bool),
        np.array(shares, dtype=np.float32),
        np.array(swaps, dtype=np.int32),
        int(state.valid.size),
        time.perf_counter() - started,
        int(frame.shape[1]),
        max(frame_count(path) - reference_frame - len(fields), 0),  # every frame from the reference on has a field
    )


def code_digest(*modules: object) -> str:
    """SHA-256 of the source files of `modules` (module objects): a cached result is stale once the
    code it came from changes."""
    digest = hashlib.sha256()
    for module in modules:
        digest.update(Path(module.__file__).read_bytes())
    return digest.hexdigest()


def _fields_digest() -> str:
    """:func:`code_digest` of the code a cached field comes from: the perception modules, the checks they
    share (reference_markers), the frame crop and this module (reading frames, rounding to float16).
    It held the perception modules alone: fields rounded by another float16_px were read as current."""
    return code_digest(detection, tracking, field_module, perception, reference_markers, frame_crop,
                       sys.modules[__name__])


def video_key(video: Path, reference_frame: int, crop: FrameCrop | None) -> list:
    """What a video's cached results depend on besides the code: the file (path, size, mtime), the
    reference frame and the crop (left out when there is none, so entries cached before crops stay
    valid)."""
    stat = video.stat()
    key = [str(video.resolve()), stat.st_size, stat.st_mtime_ns, reference_frame]
    return key if crop is None else [*key, list(crop.borders), crop.size and list(crop.size)]


def cache_path(cache_dir: str | Path, video: Path, reference_frame: int = 1, crop: FrameCrop | None = None) -> Path:
    """Where the fields of ``video`` are cached: one .npz per video, named after :func:`video_key` and the
    code the fields come from (:func:`_fields_digest`), so a stale entry is never read."""
    text = json.dumps([CACHE_VERSION, *video_key(video, reference_frame, crop), _fields_digest()])
    return Path(cache_dir) / f"{cache_stem(video)}__{hashlib.sha256(text.encode()).hexdigest()[:16]}.npz"


def cache_stem(video: Path) -> str:
    """The readable start of a video's cache file names: its two parent folders and its name without the
    suffix, joined by "__" ("blue_mug__exp_num_4__camera_0")."""
    return "__".join((*video.parts[-3:-1], video.stem))


def cache_folder(cache_dir: str | Path | None) -> Path | None:
    """``cache_dir`` as a writable folder, created when missing (None: no cache); ValueError naming it when
    it is a file or cannot be created or written, before any video is decoded."""
    if cache_dir is None:
        return None
    path = Path(cache_dir)
    if path.exists() and not path.is_dir():
        raise ValueError(f"cache folder {path} is a file")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"cache folder {path} cannot be created: {exc.strerror or exc}") from exc
    if not os.access(path, os.W_OK | os.X_OK):
        raise ValueError(f"cache folder {path} is not writable")
    return path


def read_cached(path: Path, load: Callable[[Path], T]) -> T | None:
    """``load(path)`` of a cache file, or None when there is none or it cannot be read (damaged on the
    disk, cut short by a copy): that one is named in a warning, and the caller computes it again."""
    if not path.is_file():
        return None
    try:
        return load(path)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        log.warning("cache file %s cannot be read (%s: %s): computing it again", path, type(exc).__name__, exc)
        return None


def save_video_fields(path: Path, value: VideoFields) -> None:
    """Write ``value`` to ``path`` (.npz, atomically)."""
    write_atomically(path, lambda tmp: np.savez_compressed(
        tmp, fields=value.fields, field_valid=value.field_valid, valid_share=value.valid_share,
        swaps=value.swaps, n_markers=value.n_markers, seconds=value.seconds, width_px=value.width_px,
        missing_frames=value.missing_frames))


def load_video_fields(path: Path) -> VideoFields:
    """Read a file written by :func:`save_video_fields`."""
    with np.load(path) as data:
        return VideoFields(data["fields"], data["field_valid"], data["valid_share"], data["swaps"],
                           int(data["n_markers"]), float(data["seconds"]), int(data["width_px"]),
                           int(data["missing_frames"]))


def _cached_fields(video: Path, cache_dir: str | Path | None, reference_frame: int,
                   crop: FrameCrop | None) -> VideoFields:
    """Fields of one video, read from / written to the cache when there is a cache folder."""
    cached = None if cache_dir is None else cache_path(cache_dir, video, reference_frame, crop)
    if cached is not None and (value := read_cached(cached, load_video_fields)) is not None:
        return value
    value = video_fields(video, reference_frame=reference_frame, crop=crop)
    if cached is not None:
        save_video_fields(cached, value)
    return value


VideoKey = tuple[str, str]  # (trial name, camera)
TrialFields = dict[VideoKey, VideoFields]


def require_frames(fields: TrialFields, minimum: int) -> None:
    """ValueError naming every video of ``fields`` with fewer than ``minimum`` frames from the reference on
    (the reference included): a grasp that short is outside anything a model was trained on, and judging
    it would report a decision that no frame supports."""
    short = [f"{trial} {camera} ({value.fields.shape[0]})" for (trial, camera), value in fields.items()
             if value.fields.shape[0] < minimum]
    if short:
        raise ValueError(f"{len(short)} video(s) too short to judge, fewer than {minimum} frames judged from the "
                         f"reference on (frames in brackets): {', '.join(short)}")


def map_videos(trials: Sequence[Trial], compute: Callable[[Path], T], workers: int = 1, progress: bool = True,
               desc: str = "videos") -> dict[VideoKey, T]:
    """``compute(video)`` of every camera of every trial, keyed (trial name, camera), in ``workers``
    processes (1 = this one; ``compute`` must then be picklable: a module-level function or a
    functools.partial of one). One progress bar (in frames) covers the whole set. ValueError when
    ``workers`` < 1."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    videos = [(t.name, cam, path) for t in trials for cam, path in t.videos.items()]
    sizes = [frame_count(path) for _, _, path in videos]
    out: dict[VideoKey, T] = {}
    with tqdm(total=sum(sizes), unit="frame", desc=desc, disable=not progress) as bar, (
        ProcessPoolExecutor(workers) if workers > 1 else nullcontext()
    ) as pool:
        paths = [path for _, _, path in videos]
        results = map(compute, paths) if pool is None else pool.map(compute, paths)
        for (name, cam, _), size, value in zip(videos, sizes, results):
            out[(name, cam)] = value
            bar.update(size)
    return out


def trial_fields(
    trials: Sequence[Trial],
    cache_dir: str | Path | None = None,
    reference_frame: int = 1,
    workers: int = 1,
    progress: bool = True,
    crop: FrameCrop | None = None,
) -> TrialFields:
    """Fields of every camera of every trial, keyed (trial name, camera), the frames cut by ``crop``
    when given (raw recordings, see :func:`read_frames`).

    cache_dir: folder for one .npz per video (None: no cache; ValueError naming it when it cannot be
    written, see :func:`cache_folder`). workers: processes (1 = this one).
    One progress bar (in frames) covers the whole set. A video whose decoding stops before the frames its
    container lists is logged as a warning, naming it (see ``VideoFields.missing_frames``).
    """
    compute = partial(_cached_fields, cache_dir=cache_folder(cache_dir), reference_frame=reference_frame, crop=crop)
    fields = map_videos(trials, compute, workers, progress, "fields")
    for (name, camera), value in fields.items():
        if value.missing_frames:
            log.warning("trial %s %s: the last %d frames its video lists could not be decoded (a truncated or "
                        "damaged file?): it is judged on the %d frames from the reference on", name, camera,
                        value.missing_frames, value.fields.shape[0])
    return fields


def tracking_quality(fields: TrialFields) -> dict[str, object]:
    """Whole-set tracking quality: videos, frames, markers per video (mean), share of markers
    valid per frame (mean, 1st percentile, min), frames with >= 1 swap flagged and swaps per
    1000 frames, invalid fields, perception time per frame (ms), and ``short_videos``: "trial
    camera" -> frames its container lists but that could not be decoded, for every such video."""
    shares = np.concatenate([v.valid_share for v in fields.values()])
    swaps = np.concatenate([v.swaps for v in fields.values()])
    frames = int(shares.size)
    return {
        "videos": len(fields),
        "frames": frames,
        "markers_mean": float(np.mean([v.n_markers for v in fields.values()])),
        "valid_share_mean": float(shares.mean()),
        "valid_share_p01": float(np.percentile(shares, 1)),
        "valid_share_min": float(shares.min()),
        "frames_with_swaps": int(np.count_nonzero(swaps)),
        "swaps_per_1000_frames": float(1e3 * swaps.sum() / frames),
        "invalid_fields": int(sum(np.count_nonzero(~v.field_valid) for v in fields.values())),
        "ms_per_frame": float(1e3 * sum(v.seconds for v in fields.values()) / frames),
        "short_videos": {f"{name} {camera}": v.missing_frames for (name, camera), v in fields.items()
                         if v.missing_frames},
    }
