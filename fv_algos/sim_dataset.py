"""The simulated slip dataset: random scenarios -> simulated camera -> real perception -> fields.

Follows the paper's protocol: S raw sequences (1,600 in the paper) of F = 15 frames at 15 Hz,
half slip (translational, rotational, incipient) and half no slip (pressing, holding, shear
without slip), on the 12 shapes of :mod:`fv_algos.sim.objects`. Each sequence is rendered by
:class:`~fv_algos.sim.sensor.SimSensor`; a rest frame of the unloaded skin is rendered first
and given to :meth:`Perception.reset`, then every scenario frame goes through
:meth:`Perception.step` (detect, track, interpolate: the fields a real sensor would yield, not
ground-truth ones), giving fields (F, 30, 30, 3) float32 px (dx, dy, magnitude).

With ``grasps``, each of the S draws is instead a whole grasp as the main job's camera plays it
(:func:`fv_algos.sim.scene.grasp_scene`: pressed from rest, ``GRASP_MOTION_S`` of a scenario of that
kind, released, at rest), cut into sequences of F frames starting every ``GRASP_SEGMENT_STEP`` frames,
every frame labelled with its truth: windows then straddle the changes of the truth (a slide that
stops, a release) and are labelled by their last frame, which the paper's sequences never show.

Reproducibility: sequence (or grasp) ``i`` depends only on (seed, i) (its generator is
``numpy.random.default_rng([seed, i])``) and its kind comes from a balanced plan shuffled by
``seed``, so any chunking over worker processes gives identical data.
"""
from __future__ import annotations

import multiprocessing
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from tqdm import tqdm

from fv_algos.perception import Perception, PerceptionParams
from fv_algos.sim.objects import SHAPES, shape_name
from fv_algos.sim.scene import DEFAULT_RENDER_EFFECTS, NON_SLIP_KINDS, SLIP_KINDS, Scene, grasp_scene, random_scenario
from fv_algos.sim.sensor import SceneRunner, SensorParams, SimSensor
from fv_algos.slip.windows import SequenceSet

OBJECT_NAMES: tuple[str, ...] = tuple(SHAPES)
"""Object id i of a sequence is the shape OBJECT_NAMES[i]."""

_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
GRASP_MOTION_S = (2.0, 4.0)  # a grasp's scenario lasts one of these, s: the main job's 60 frames at 30 and 15 fps
GRASP_SEGMENT_STEP = 10  # frames between the starts of a grasp's sequences
SLIP_FROM_FRAME = 3  # a slip sequence slips from this frame on (random_scenario's kinds: frame 3 at the latest)
MAX_DRAWS = 20  # scenarios drawn for one sequence at most, until one's truth agrees with its kind


@dataclass(frozen=True)
class SimDatasetConfig:
    """What to generate.

    n_sequences: raw sequences S (>= 2); floor(S / 2) slip, the rest no slip.
    n_frames: frames per sequence F (>= 4).
    fps: frame rate, Hz.
    seed: master seed; sequence i uses default_rng([seed, i]).
    preset: perception preset name (PerceptionParams.preset).
    render_effects: renderer effects of every scenario (fv_algos.sim.render.EFFECTS).
    grasps: each of the S draws is a whole grasp, cut into sequences with per-frame labels (module doc).
    """

    n_sequences: int = 1600
    n_frames: int = 15
    fps: float = 15.0
    seed: int = 0
    preset: str = "default"
    render_effects: tuple[str, ...] = tuple(sorted(DEFAULT_RENDER_EFFECTS))
    grasps: bool = False

    def __post_init__(self) -> None:
        if self.n_sequences < 2:
            raise ValueError(f"n_sequences must be >= 2, got {self.n_sequences}")
        if self.n_frames < 4:
            raise ValueError(f"n_frames must be >= 4, got {self.n_frames}")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps must be finite and > 0, got {self.fps}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        PerceptionParams.preset(self.preset)  # raises ValueError naming the valid presets


@dataclass(frozen=True)
class SimSequence:
    """One generated sequence: fields (F, H, W, 3) float32 px, its kind, label (1 = slip),
    object id (index into OBJECT_NAMES), per-frame true slip flags (F,) bool, the number
    of frames whose field perception flagged invalid (stored as zeros) and the camera's frame
    width (px, the scale of the fields)."""

    fields: np.ndarray
    kind: str
    label: int
    object_id: int
    frame_slip: np.ndarray
    invalid_frames: int
    width_px: int


def fields_nbytes(config: SimDatasetConfig) -> int:
    """Bytes the set's fields take while :func:`generate` stacks them, at most: every sequence's float32
    fields (F, H, W, 3) once in the list of sequences and once stacked. A grasp counts the sequences of
    its longest form (``GRASP_MOTION_S[-1]`` of scenario and a second and a half of press, shear, twist,
    release and rest)."""
    rows, cols = PerceptionParams.preset(config.preset).interpolation.grid_shape
    per_draw = 1
    if config.grasps:
        frames = int(np.ceil((GRASP_MOTION_S[-1] + 1.6) * config.fps))
        per_draw = max(0, (frames - config.n_frames) // GRASP_SEGMENT_STEP + 1)
    return 2 * config.n_sequences * per_draw * config.n_frames * rows * cols * 3 * 4


def kind_plan(n_sequences: int, seed: int) -> list[str]:
    """Scenario kind of every sequence: floor(S / 2) slip kinds and the rest no-slip kinds, each
    group cycling through its three kinds, in an order shuffled by ``seed``."""
    kinds = [
        (SLIP_KINDS if i % 2 else NON_SLIP_KINDS)[(i // 2) % len(SLIP_KINDS)] for i in range(n_sequences)
    ]
    order = np.random.default_rng(seed).permutation(n_sequences)
    return [kinds[i] for i in order]


def _perceive(scene: Scene, rng: np.random.Generator, preset: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Render ``scene`` (camera noise seeded from ``rng``) and run perception on it from the skin at rest:
    fields (F, 30, 30, 3) float32 px, true slip (F,) bool, field flagged invalid (F,) bool, and the
    camera's frame width (px)."""
    sensor = SimSensor(scene, seed=int(rng.integers(2**31)))
    rest_markers = np.column_stack([sensor.markers_ref_mm, np.zeros(len(sensor.markers_ref_mm))])
    perception = Perception(PerceptionParams.preset(preset))  # type: ignore[arg-type]
    perception.reset(sensor.renderer.render(rest_markers).image)
    fields, frame_slip, invalid = [], [], []
    for frame in sensor:
        _, dense = perception.step(frame.image)
        fields.append(dense.field)
        frame_slip.append(frame.truth.is_slip)
        invalid.append(not dense.valid)
    return np.stack(fields), np.array(frame_slip, dtype=bool), np.array(invalid, dtype=bool), sensor.camera.width


def _scenario_of_kind(rng: np.random.Generator, kind: str, config: SimDatasetConfig) -> Scene:
    """A random scenario of ``kind`` whose mechanics' truth is what its label says: a slip kind slips on
    every frame from ``SLIP_FROM_FRAME`` on, so that every window of it holds slip; a no-slip kind never
    slips. A draw that misses (e.g. an "incipient" shear on a bottle cap's lip or an edge, whose slip zone
    stays under half the contact: truth "stick"), or whose mechanics stop with an error, is drawn again
    from ``rng``."""
    params = SensorParams()
    for _ in range(MAX_DRAWS):
        scene = random_scenario(rng, kind, config.n_frames, config.fps, frozenset(config.render_effects))
        try:
            slip = np.array([frame.state.is_slip for frame in SceneRunner(scene, params.skin, params.contact)])
        except ValueError:  # mechanics the scene cannot play (an object slid off the skin): drawn again
            continue
        if slip[SLIP_FROM_FRAME:].all() if kind in SLIP_KINDS else not slip.any():
            return scene
    raise RuntimeError(f"no {kind} scenario in {MAX_DRAWS} draws slipped as its label says")


def simulate_sequence(config: SimDatasetConfig, index: int, kind: str) -> SimSequence:
    """Render sequence ``index`` of kind ``kind`` and run perception on it (deterministic in
    (config.seed, index)); its label is its kind's (:func:`_scenario_of_kind` makes the truth agree)."""
    rng = np.random.default_rng([config.seed, index])
    scene = _scenario_of_kind(rng, kind, config)
    fields, frame_slip, invalid, width = _perceive(scene, rng, config.preset)
    return SimSequence(fields, kind, int(kind in SLIP_KINDS), OBJECT_NAMES.index(shape_name(scene.obj)), frame_slip,
                       int(invalid.sum()), width)


def simulate_grasp(config: SimDatasetConfig, index: int, kind: str) -> list[SimSequence]:
    """Grasp ``index``: a scenario of kind ``kind`` lasting one of ``GRASP_MOTION_S``, played as
    :func:`fv_algos.sim.scene.grasp_scene` plays it, cut into sequences of ``config.n_frames`` frames
    starting every ``GRASP_SEGMENT_STEP`` frames, each labelled slip when any of its frames slips
    (deterministic in (config.seed, index))."""
    rng = np.random.default_rng([config.seed, index])
    motion_frames = int(round(GRASP_MOTION_S[int(rng.integers(len(GRASP_MOTION_S)))] * config.fps))
    scenario = random_scenario(rng, kind, motion_frames, config.fps, frozenset(config.render_effects))
    fields, frame_slip, invalid, width = _perceive(grasp_scene(scenario), rng, config.preset)
    object_id = OBJECT_NAMES.index(shape_name(scenario.obj))
    cuts = [slice(start, start + config.n_frames)
            for start in range(0, len(fields) - config.n_frames + 1, GRASP_SEGMENT_STEP)]
    return [SimSequence(fields[cut], kind, int(frame_slip[cut].any()), object_id, frame_slip[cut],
                        int(invalid[cut].sum()), width) for cut in cuts]


def _simulate_job(job: tuple[SimDatasetConfig, int, str]) -> list[SimSequence]:
    config, index, kind = job
    return simulate_grasp(config, index, kind) if config.grasps else [simulate_sequence(config, index, kind)]


def _single_threaded_workers() -> None:
    cv2.setNumThreads(1)


def iter_sequences(config: SimDatasetConfig, workers: int = 1) -> Iterator[list[SimSequence]]:
    """The sequences of draws 0 .. S-1 in order, one list per draw (one sequence, or a grasp's), computed
    in ``workers`` processes (1: in this process).

    Worker processes are spawned (safe next to torch/OpenMP) with one BLAS/OpenMP/OpenCV thread
    each, so W workers use about W cores; as with any spawned pool, a calling script needs the
    ``if __name__ == "__main__":`` guard.
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    jobs = [(config, i, kind) for i, kind in enumerate(kind_plan(config.n_sequences, config.seed))]
    if workers == 1:
        yield from map(_simulate_job, jobs)
        return
    saved = {name: os.environ.get(name) for name in _THREAD_ENV}
    os.environ.update({name: "1" for name in _THREAD_ENV})  # inherited by the spawned workers
    try:
        context = multiprocessing.get_context("spawn")
        with context.Pool(workers, initializer=_single_threaded_workers) as pool:
            chunk = max(1, min(8, len(jobs) // (4 * workers)))
            yield from pool.imap(_simulate_job, jobs, chunksize=chunk)
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def generate(config: SimDatasetConfig, workers: int = 1, progress: bool = True) -> SequenceSet:
    """The whole dataset as a :class:`SequenceSet` (fields (S, F, 30, 30, 3) float16 px).

    metadata holds: source "sim", ``frame_width_px`` (the camera's), the config, object_names, per-sequence ``kinds`` and
    ``frame_slip`` (true per-frame slip flags as 0/1 lists), ``invalid_frames`` (fields perception
    flagged invalid, summed over the sequences: a grasp's overlapping sequences count a frame in each), ``generation_s`` (wall time) and ``workers``. With ``config.grasps`` the
    set also has ``frame_labels`` (the same flags), by which its windows are labelled.
    """
    started = time.perf_counter()
    sequences = [sequence for draw in tqdm(iter_sequences(config, workers), total=config.n_sequences,
                                           desc="simulate", unit="grasp" if config.grasps else "seq",
                                           disable=not progress) for sequence in draw]
    elapsed = time.perf_counter() - started
    return to_sequence_set(sequences, config, {"generation_s": round(elapsed, 2), "workers": workers})


def to_sequence_set(sequences: Sequence[SimSequence], config: SimDatasetConfig,
                    extra: dict[str, object] | None = None) -> SequenceSet:
    """Stack generated sequences into a :class:`SequenceSet` with the metadata of :func:`generate`."""
    if not sequences:
        raise ValueError(f"no sequences of {config.n_frames} frames: every grasp was shorter (--frames)" if config.grasps
                         else "no sequences to stack")
    widths = sorted({s.width_px for s in sequences})
    if len(widths) > 1:
        raise ValueError(f"sequences of cameras {widths} px wide: one set holds the fields of one frame width")
    metadata: dict[str, object] = {
        "source": "sim",
        "frame_width_px": widths[0],
        "config": {**config.__dict__, "render_effects": list(config.render_effects)},
        "object_names": list(OBJECT_NAMES),
        "kinds": [s.kind for s in sequences],
        "frame_slip": [s.frame_slip.astype(int).tolist() for s in sequences],
        "invalid_frames": int(sum(s.invalid_frames for s in sequences)),
        **(extra or {}),
    }
    return SequenceSet(
        np.stack([s.fields for s in sequences]),
        np.array([s.label for s in sequences], dtype=np.int64),
        np.array([s.object_id for s in sequences], dtype=np.int64),
        metadata,
        np.stack([s.frame_slip for s in sequences]) if config.grasps else None,
    )
