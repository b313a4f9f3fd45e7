"""Raw displacement-field sequences -> 10-frame windows, train/test splits, compact storage.

A sequence set holds S raw sequences of F frames each, ``fields`` (S, F, H, W, 3) float16 in px
(dx, dy, magnitude), one label per sequence (0 = no slip, 1 = slip) and an object id per sequence,
and may hold a label per frame (segments of whole grasps, whose truth changes within them): a window
is then labelled by its last frame, the slip detector's question (is it slipping now).
Windows are never copied out: a :class:`WindowSet` is an index (sequence, start frame) into the
sequences and :meth:`WindowSet.get` gathers a batch (B, T, H, W, 3) float32 on demand.

The paper cuts 5 windows of 10 frames (stride 1) from each 15-frame sequence (8,000 windows from
1,600 sequences) although 15 - 10 + 1 = 6 fit; we take the first ``per_sequence`` starts
(0..4 by default), so frame 14 is not used.

On disk (:func:`save_sequences` / :func:`load_sequences`): one ``.npz`` with ``fields`` float16,
``labels`` int64, ``object_ids`` int64, ``frame_labels`` int64 when the set has them, and ``metadata``
(a JSON string with the format name and version and any user metadata such as the generating seed).
"""
from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fv_algos.atomic_file import write_atomically

DATASET_FORMAT = "fv-slip-sequences"
DATASET_FORMAT_VERSION = 1
FLOAT16_MAX = float(np.finfo(np.float16).max)
SPLIT_KINDS = ("random", "sequence", "object")


@dataclass
class SequenceSet:
    """Labelled raw sequences.

    fields: (S, F, H, W, 3) float16, px; finite and |value| <= 65504 (float16 range).
    labels: (S,) int64 in {0, 1}.
    object_ids: (S,) int64, which object each sequence was recorded with.
    metadata: JSON-serialisable dict (e.g. {"seed": 0, "source": "synthetic"}); ``frame_width_px``, when
        the fields come from a camera, is its frame width (the px the fields are in).
    frame_labels: (S, F) int64 in {0, 1}, the truth of every frame, or None (every frame of a sequence
        has its label).
    """

    fields: np.ndarray
    labels: np.ndarray
    object_ids: np.ndarray
    metadata: dict[str, object] = field(default_factory=dict)
    frame_labels: np.ndarray | None = None

    def __post_init__(self) -> None:
        values = np.asarray(self.fields)
        if values.ndim != 5 or values.shape[-1] != 3:
            raise ValueError(f"fields must have shape (S, F, H, W, 3), got {values.shape}")
        if np.issubdtype(values.dtype, np.floating) and values.dtype != np.float16:
            finite = np.isfinite(values)
            if not finite.all():
                raise ValueError(f"fields contain {int((~finite).sum())} non-finite values (NaN/inf)")
            peak = float(np.abs(values).max(initial=0.0))
            if peak > FLOAT16_MAX:
                raise ValueError(f"fields reach {peak:g} px, beyond the float16 storage range ({FLOAT16_MAX:g})")
        self.fields = values.astype(np.float16, copy=False)
        if not np.isfinite(self.fields).all():
            raise ValueError("fields contain non-finite values (NaN/inf)")
        n = self.fields.shape[0]
        self.labels = np.asarray(self.labels).astype(np.int64, copy=False)
        self.object_ids = np.asarray(self.object_ids).astype(np.int64, copy=False)
        if self.labels.shape != (n,):
            raise ValueError(f"labels must have shape ({n},) to match fields, got {self.labels.shape}")
        if self.object_ids.shape != (n,):
            raise ValueError(f"object_ids must have shape ({n},) to match fields, got {self.object_ids.shape}")
        if not np.isin(self.labels, (0, 1)).all():
            raise ValueError(f"labels must be 0 (no slip) or 1 (slip), got values {np.unique(self.labels).tolist()}")
        if self.frame_labels is not None:
            self.frame_labels = np.asarray(self.frame_labels).astype(np.int64, copy=False)
            if self.frame_labels.shape != self.fields.shape[:2]:
                raise ValueError(f"frame_labels must have shape {self.fields.shape[:2]} (sequences, frames), "
                                 f"got {self.frame_labels.shape}")
            if not np.isin(self.frame_labels, (0, 1)).all():
                raise ValueError(f"frame_labels must be 0 (no slip) or 1 (slip), got values "
                                 f"{np.unique(self.frame_labels).tolist()}")

    def per_frame_labels(self) -> np.ndarray:
        """(S, F) int64 label of every frame: ``frame_labels``, or each sequence's label on all its frames."""
        if self.frame_labels is not None:
            return self.frame_labels
        return np.repeat(self.labels[:, None], self.n_frames, axis=1)

    @property
    def n_frames(self) -> int:
        """F, frames per raw sequence."""
        return int(self.fields.shape[1])

    @property
    def grid(self) -> int:
        """H (= W expected by the models)."""
        return int(self.fields.shape[2])

    @property
    def frame_width_px(self) -> int | None:
        """Width (px) of the camera frames the fields were measured in (metadata ``frame_width_px``);
        None for fields of no camera, or sets saved before it was recorded."""
        width = self.metadata.get("frame_width_px")
        return int(width) if width else None


def save_sequences(path: str | Path, sequences: SequenceSet) -> Path:
    """Write ``sequences`` to one compressed ``.npz``, whole or not at all; returns the path. A name
    without that suffix gets it added (``sim.v1`` -> ``sim.v1.npz``: two such names never share a file)."""
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    meta = {"format": DATASET_FORMAT, "format_version": DATASET_FORMAT_VERSION, "user": sequences.metadata}
    frame_labels = {} if sequences.frame_labels is None else {"frame_labels": sequences.frame_labels}
    write_atomically(path, lambda tmp: np.savez_compressed(
        tmp,
        fields=sequences.fields,
        labels=sequences.labels,
        object_ids=sequences.object_ids,
        metadata=np.array(json.dumps(meta)),
        **frame_labels,
    ))
    return path


def load_sequences(path: str | Path) -> SequenceSet:
    """Read a file written by :func:`save_sequences`; ValueError/FileNotFoundError say what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"slip dataset not found: {path}")
    try:
        data = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise ValueError(f"{path} is not a slip dataset .npz file (fv dataset sim writes them): {exc}") from exc
    if not isinstance(data, np.lib.npyio.NpzFile):  # a lone .npy array
        raise ValueError(f"{path} is one array, not a slip dataset .npz file (fv dataset sim writes them)")
    with data:
        arrays = {key: data[key] for key in data.files}
    missing = sorted({"fields", "labels", "object_ids", "metadata"} - set(arrays))
    if missing:
        raise ValueError(f"{path} is missing arrays {missing}")
    try:
        meta = json.loads(str(arrays["metadata"]))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: metadata is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != DATASET_FORMAT:
        raise ValueError(f"{path}: metadata format is not {DATASET_FORMAT!r}")
    if meta.get("format_version") != DATASET_FORMAT_VERSION:
        raise ValueError(
            f"{path}: dataset format version {meta.get('format_version')!r} is not supported "
            f"(expected {DATASET_FORMAT_VERSION})"
        )
    if arrays["fields"].dtype != np.float16:
        raise ValueError(f"{path}: fields must be stored as float16, found {arrays['fields'].dtype}")
    return SequenceSet(arrays["fields"], arrays["labels"], arrays["object_ids"], dict(meta.get("user", {})),
                       arrays.get("frame_labels"))


@dataclass
class WindowSet:
    """Windows of ``window`` consecutive frames cut from a :class:`SequenceSet`.

    sequence: (N,) int64, which sequence each window comes from.
    start: (N,) int64, first frame of each window.
    """

    sequences: SequenceSet
    window: int
    sequence: np.ndarray
    start: np.ndarray

    def __len__(self) -> int:
        return int(self.sequence.shape[0])

    @property
    def labels(self) -> np.ndarray:
        """(N,) int64 label of each window: its last frame's when the sequences have frame labels, else
        its sequence's."""
        if self.sequences.frame_labels is None:
            return self.sequences.labels[self.sequence]
        return self.sequences.frame_labels[self.sequence, self.start + self.window - 1]

    @property
    def object_ids(self) -> np.ndarray:
        """(N,) int64 object id of each window."""
        return self.sequences.object_ids[self.sequence]

    def get(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Windows ``rows`` -> (windows (B, T, H, W, 3) float32 px, labels (B,) int64)."""
        rows = np.asarray(rows, dtype=np.int64)
        if rows.ndim != 1 or (rows.size and (rows.min() < 0 or rows.max() >= len(self))):
            raise ValueError(f"rows must be a 1-D array of indices in [0, {len(self)})")
        frames = self.start[rows, None] + np.arange(self.window)
        batch = self.sequences.fields[self.sequence[rows, None], frames]
        return batch.astype(np.float32), self.labels[rows]


def make_windows(sequences: SequenceSet, window: int = 10, per_sequence: int | None = 5, stride: int = 1) -> WindowSet:
    """Cut windows of ``window`` frames, ``stride`` apart, keeping the first ``per_sequence`` of
    each sequence (None keeps all that fit). Rows are ordered sequence-major."""
    if window < 1 or stride < 1:
        raise ValueError(f"window and stride must be >= 1, got window={window}, stride={stride}")
    available = (sequences.n_frames - window) // stride + 1
    if available < 1:
        raise ValueError(f"sequences have {sequences.n_frames} frames, fewer than window={window}")
    count = available if per_sequence is None else per_sequence
    if not 1 <= count <= available:
        raise ValueError(
            f"per_sequence={per_sequence} windows do not fit: {sequences.n_frames} frames allow "
            f"{available} windows of {window} at stride {stride}"
        )
    n_seq = sequences.fields.shape[0]
    seq = np.repeat(np.arange(n_seq, dtype=np.int64), count)
    start = np.tile(np.arange(count, dtype=np.int64) * stride, n_seq)
    return WindowSet(sequences, window, seq, start)


@dataclass
class Split:
    """Train/test partition of a window set: ``train`` and ``test`` are (N_train,), (N_test,)
    int64 window rows; ``kind`` is how they were drawn (see :func:`split_windows`)."""

    windows: WindowSet
    train: np.ndarray
    test: np.ndarray
    kind: str


def split_windows(windows: WindowSet, kind: str = "random", test_fraction: float = 0.1, seed: int = 0) -> Split:
    """Partition ``windows`` into train and test.

    kind "random": the paper's split, windows shuffled 90/10, so overlapping windows of one
        sequence land on both sides (optimistic).
    kind "sequence": whole raw sequences held out.
    kind "object": whole objects held out, objects drawn at random until at least
        ``test_fraction`` of the sequences are in the test set.
    """
    if kind not in SPLIT_KINDS:
        raise ValueError(f"split kind must be one of {SPLIT_KINDS}, got {kind!r}")
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"test_fraction must be in (0, 1), got {test_fraction}")
    rng = np.random.default_rng(seed)
    n = len(windows)
    if kind == "random":
        order = rng.permutation(n)
        n_test = int(round(test_fraction * n))
        test_mask = np.zeros(n, dtype=bool)
        test_mask[order[:n_test]] = True
    else:
        groups = windows.sequence if kind == "sequence" else windows.object_ids
        unique = rng.permutation(np.unique(groups))
        if unique.size < 2:
            raise ValueError(f"a {kind!r} split needs at least 2 distinct {kind}s, got {unique.size}")
        if kind == "sequence":
            held = unique[: max(1, int(round(test_fraction * unique.size)))]
        else:
            per_object = np.array([np.count_nonzero(groups == g) for g in unique])
            n_held = int(np.searchsorted(np.cumsum(per_object), test_fraction * n)) + 1
            held = unique[: min(n_held, unique.size - 1)]
        test_mask = np.isin(groups, held)
    train, test = np.flatnonzero(~test_mask), np.flatnonzero(test_mask)
    if train.size == 0 or test.size == 0:
        shown = "paper" if kind == "random" else kind  # as `fv train --split` names it (it read 'random')
        raise ValueError(f"{shown!r} split with test_fraction={test_fraction} leaves an empty side (train {train.size} "
                         f"/ test {test.size} windows)")
    return Split(windows, train, test, kind)


def _layout(sequences: SequenceSet) -> str:
    """What sequences must share to be windowed together, in words."""
    width = sequences.frame_width_px
    return (f"{sequences.n_frames} frames on a {sequences.grid} grid, "
            + (f"frames {width} px wide" if width else "frame width unknown"))


def with_extra_training(split: Split, extra: SequenceSet) -> Split:
    """``split`` with the windows of every ``extra`` sequence, cut at the starts of the split's own, added
    to its training rows; its test rows stay those of its own sequences (the figures stay comparable with
    a split without extra data). In an object split, extra sequences of the test objects are left out.
    ValueError when the two sets differ in frames per sequence, grid or frame width."""
    own, windows = split.windows.sequences, split.windows
    if (extra.n_frames, extra.grid, extra.frame_width_px) != (own.n_frames, own.grid, own.frame_width_px):
        raise ValueError(f"extra sequences ({_layout(extra)}) do not join the sequences of the split ({_layout(own)})")
    joined = SequenceSet(np.concatenate([own.fields, extra.fields]), np.concatenate([own.labels, extra.labels]),
                         np.concatenate([own.object_ids, extra.object_ids]), own.metadata,
                         np.concatenate([own.per_frame_labels(), extra.per_frame_labels()]))
    starts = windows.start[windows.sequence == windows.sequence[0]]  # make_windows cuts every sequence alike
    extra_sequence = np.repeat(np.arange(len(own.labels), len(joined.labels)), starts.size)
    joined_windows = WindowSet(joined, windows.window, np.concatenate([windows.sequence, extra_sequence]),
                               np.concatenate([windows.start, np.tile(starts, len(extra.labels))]))
    added = np.arange(len(windows), len(joined_windows))
    if split.kind == "object":
        added = added[~np.isin(joined_windows.object_ids[added], windows.object_ids[split.test])]
    return Split(joined_windows, np.concatenate([split.train, added]), split.test, split.kind)


@dataclass(frozen=True)
class SyntheticConfig:
    """Synthetic displacement-field sequences for tests and benchmarks (until the simulated
    sensor provides data).

    Each sequence is a smooth random field (Gaussian low-pass spectrum, length scale set by the
    object) with peak amplitude in the ``amplitude_px`` range. Both classes: the amplitude grows
    linearly to full over a random 1..n_frames//2 frames, then holds. No slip: the pattern keeps
    its shape. Slip: the pattern also translates at ``slip_speed`` cells/frame in a random direction and decorrelates
    (rotates in function space towards a second random field) at ``decorrelation`` rad/frame.
    Gaussian noise of ``noise_px`` is added to dx and dy; magnitude is hypot(dx, dy).
    """

    n_frames: int = 15
    grid: int = 30
    n_objects: int = 8
    amplitude_px: tuple[float, float] = (1.0, 8.0)
    slip_speed: tuple[float, float] = (0.05, 0.6)
    decorrelation: tuple[float, float] = (0.0, 0.08)
    noise_px: float = 0.1


def synthetic_sequences(n_sequences: int, config: SyntheticConfig = SyntheticConfig(), seed: int = 0) -> SequenceSet:
    """``n_sequences`` synthetic sequences, half slip, reproducible from ``seed``."""
    if n_sequences < 2:
        raise ValueError(f"n_sequences must be >= 2, got {n_sequences}")
    rng = np.random.default_rng(seed)
    g, f = config.grid, config.n_frames
    size = 2 * g  # periodic canvas; the visible grid is its top-left corner
    labels = rng.permutation(np.arange(n_sequences) % 2).astype(np.int64)
    object_ids = rng.integers(0, config.n_objects, n_sequences).astype(np.int64)
    length_scale = 2.0 + 4.0 * (np.arange(config.n_objects) / max(config.n_objects - 1, 1))  # cells
    k = np.fft.fftfreq(size)
    ky, kx = np.meshgrid(k, k, indexing="ij")
    out = np.empty((n_sequences, f, g, g, 3), dtype=np.float16)
    t = np.arange(f, dtype=np.float64)
    for s in range(n_sequences):
        envelope = np.exp(-2.0 * (np.pi * length_scale[object_ids[s]]) ** 2 * (kx**2 + ky**2))
        spectra = np.fft.fft2(rng.normal(size=(2, 2, size, size))) * envelope  # (pattern, dx/dy, y, x)
        ramp = rng.integers(1, f // 2 + 1)
        gain = np.minimum(1.0, (t + 1) / ramp)
        if labels[s] == 1:
            speed = rng.uniform(*config.slip_speed)
            angle = rng.uniform(0.0, 2.0 * np.pi)
            shift = speed * t[:, None] * np.array([np.sin(angle), np.cos(angle)])  # (F, 2) cells (y, x)
            theta = rng.uniform(*config.decorrelation) * t
        else:
            shift = np.zeros((f, 2))
            theta = np.zeros(f)
        phase = np.exp(-2j * np.pi * (shift[:, 0, None, None] * ky + shift[:, 1, None, None] * kx))  # (F, y, x)
        mixed = np.cos(theta)[:, None, None, None] * spectra[0] + np.sin(theta)[:, None, None, None] * spectra[1]
        disp = np.fft.ifft2(mixed * phase[:, None]).real[:, :, :g, :g]  # (F, 2, g, g)
        disp *= rng.uniform(*config.amplitude_px) / max(np.abs(disp[0]).max(), 1e-9)
        disp = disp * gain[:, None, None, None] + rng.normal(scale=config.noise_px, size=disp.shape)
        dxdy = np.moveaxis(disp, 1, -1)
        out[s, ..., :2] = dxdy
        out[s, ..., 2] = np.hypot(dxdy[..., 0], dxdy[..., 1])
    meta = {"source": "synthetic", "seed": seed, "n_sequences": n_sequences, "config": _jsonable(config)}
    return SequenceSet(out, labels, object_ids, meta)


def _jsonable(config: SyntheticConfig) -> dict[str, object]:
    return {name: list(v) if isinstance(v, tuple) else v for name, v in config.__dict__.items()}
