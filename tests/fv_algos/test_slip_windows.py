"""Windows, splits, compact storage and the synthetic generator of fv_algos.slip.windows."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fv_algos.slip.windows import (
    SequenceSet,
    SyntheticConfig,
    load_sequences,
    make_windows,
    save_sequences,
    split_windows,
    synthetic_sequences,
    with_extra_training,
)

SMALL = SyntheticConfig(n_frames=15, grid=12, n_objects=5)


@pytest.fixture(scope="module")
def sequences() -> SequenceSet:
    return synthetic_sequences(40, SMALL, seed=3)


def test_synthetic_is_reproducible_and_balanced(sequences: SequenceSet) -> None:
    again = synthetic_sequences(40, SMALL, seed=3)
    other = synthetic_sequences(40, SMALL, seed=4)
    assert np.array_equal(sequences.fields, again.fields)
    assert not np.array_equal(sequences.fields, other.fields)
    assert sequences.fields.shape == (40, 15, 12, 12, 3) and sequences.fields.dtype == np.float16
    assert np.count_nonzero(sequences.labels) == 20
    mag = np.hypot(sequences.fields[..., 0].astype(np.float32), sequences.fields[..., 1].astype(np.float32))
    assert np.allclose(sequences.fields[..., 2], mag, atol=0.01)


def test_no_slip_keeps_its_pattern_slip_changes_it(sequences: SequenceSet) -> None:
    f = sequences.fields.astype(np.float64)[..., :2]
    first, last = f[:, -6].reshape(40, -1), f[:, -1].reshape(40, -1)  # 5 frames apart
    cos = (first * last).sum(1) / np.linalg.norm(first, axis=1) / np.linalg.norm(last, axis=1)
    assert cos[sequences.labels == 0].mean() > 0.95
    assert cos[sequences.labels == 1].mean() < cos[sequences.labels == 0].mean() - 0.04


def test_windows_take_first_five_starts(sequences: SequenceSet) -> None:
    windows = make_windows(sequences)
    assert len(windows) == 200
    assert windows.start[:6].tolist() == [0, 1, 2, 3, 4, 0]
    x, y = windows.get(np.array([7]))
    assert x.shape == (1, 10, 12, 12, 3) and x.dtype == np.float32
    assert np.array_equal(x[0], sequences.fields[1, 2:12].astype(np.float32))
    assert y[0] == sequences.labels[1]
    assert len(make_windows(sequences, per_sequence=None)) == 240
    assert len(make_windows(sequences, window=5, per_sequence=None, stride=2)) == 40 * 6


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"window": 16}, "fewer than window"), ({"per_sequence": 7}, "do not fit"), ({"stride": 0}, ">= 1")],
)
def test_make_windows_rejects_bad_arguments(sequences: SequenceSet, kwargs: dict[str, int], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make_windows(sequences, **kwargs)


def test_get_rejects_out_of_range_rows(sequences: SequenceSet) -> None:
    with pytest.raises(ValueError, match="rows"):
        make_windows(sequences).get(np.array([200]))


def test_random_split_mixes_sequences_others_do_not(sequences: SequenceSet) -> None:
    windows = make_windows(sequences)
    rnd = split_windows(windows, "random", 0.1, seed=1)
    assert rnd.test.size == 20 and rnd.train.size == 180
    assert np.intersect1d(windows.sequence[rnd.train], windows.sequence[rnd.test]).size > 0
    seq = split_windows(windows, "sequence", 0.1, seed=1)
    assert np.intersect1d(windows.sequence[seq.train], windows.sequence[seq.test]).size == 0
    assert seq.test.size == 20
    obj = split_windows(windows, "object", 0.1, seed=1)
    assert np.intersect1d(windows.object_ids[obj.train], windows.object_ids[obj.test]).size == 0
    assert obj.test.size >= 20
    for split in (rnd, seq, obj):
        assert np.union1d(split.train, split.test).size == len(windows)
    assert np.array_equal(split_windows(windows, "object", 0.1, seed=1).test, obj.test)


def test_split_rejects_bad_kind_and_fraction(sequences: SequenceSet) -> None:
    windows = make_windows(sequences)
    with pytest.raises(ValueError, match="split kind"):
        split_windows(windows, "by_colour")
    with pytest.raises(ValueError, match="test_fraction"):
        split_windows(windows, "random", 1.5)
    one_object = SequenceSet(sequences.fields, sequences.labels, np.zeros(40))
    with pytest.raises(ValueError, match="at least 2"):
        split_windows(make_windows(one_object), "object")


def test_save_load_round_trip(sequences: SequenceSet, tmp_path: Path) -> None:
    path = save_sequences(tmp_path / "data", sequences)
    assert path.suffix == ".npz"
    loaded = load_sequences(path)
    assert np.array_equal(loaded.fields, sequences.fields)
    assert np.array_equal(loaded.labels, sequences.labels)
    assert np.array_equal(loaded.object_ids, sequences.object_ids)
    assert loaded.metadata["seed"] == 3
    raw_bytes = sequences.fields.size * 4
    assert path.stat().st_size < raw_bytes / 2


def test_save_adds_the_suffix_and_leaves_nothing_else(sequences: SequenceSet, tmp_path: Path) -> None:
    """`sim.v1` and `sim.v2` are two files (the suffix replaced, both were `sim.npz`), and a save leaves
    no temporary file beside them."""
    first = save_sequences(tmp_path / "sim.v1", sequences)
    second = save_sequences(tmp_path / "sim.v2", SequenceSet(sequences.fields[:2], sequences.labels[:2],
                                                             sequences.object_ids[:2]))
    assert (first.name, second.name) == ("sim.v1.npz", "sim.v2.npz")
    assert len(load_sequences(first).labels) == len(sequences.labels)
    assert len(load_sequences(second).labels) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim.v1.npz", "sim.v2.npz"]


def test_load_errors_are_clear(sequences: SequenceSet, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="not found"):
        load_sequences(tmp_path / "missing.npz")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file at all")
    with pytest.raises(ValueError, match="not a slip dataset"):
        load_sequences(garbage)
    lone = tmp_path / "lone.npy"  # a TypeError before
    np.save(lone, np.arange(3))
    with pytest.raises(ValueError, match="is one array, not a slip dataset"):
        load_sequences(lone)
    partial = tmp_path / "partial.npz"
    np.savez(partial, fields=sequences.fields)
    with pytest.raises(ValueError, match="missing arrays"):
        load_sequences(partial)
    wrong = tmp_path / "wrong.npz"
    meta = json.dumps({"format": "fv-slip-sequences", "format_version": 99})
    np.savez(wrong, fields=sequences.fields, labels=sequences.labels, object_ids=sequences.object_ids, metadata=np.array(meta))
    with pytest.raises(ValueError, match="version 99"):
        load_sequences(wrong)


def test_sequence_set_validation(sequences: SequenceSet) -> None:
    f32 = sequences.fields.astype(np.float32)
    with pytest.raises(ValueError, match="shape"):
        SequenceSet(f32[..., :2], sequences.labels, sequences.object_ids)
    with pytest.raises(ValueError, match="labels must be 0"):
        SequenceSet(f32, sequences.labels + 1, sequences.object_ids)
    with pytest.raises(ValueError, match="labels must have shape"):
        SequenceSet(f32, sequences.labels[:3], sequences.object_ids)
    nan = f32.copy()
    nan[0, 0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        SequenceSet(nan, sequences.labels, sequences.object_ids)
    with pytest.raises(ValueError, match="float16 storage range"):
        SequenceSet(f32 * 1e5, sequences.labels, sequences.object_ids)


def _grasp_like(sequences: SequenceSet, change_at: int = 7) -> SequenceSet:
    """``sequences`` with per-frame labels: every sequence slips from frame ``change_at`` on."""
    frame_labels = np.zeros(sequences.fields.shape[:2], np.int64)
    frame_labels[:, change_at:] = 1
    return SequenceSet(sequences.fields, np.ones_like(sequences.labels), sequences.object_ids, {}, frame_labels)


def test_frame_labels_label_each_window_by_its_last_frame(sequences: SequenceSet, tmp_path: Path) -> None:
    grasps = _grasp_like(sequences)
    windows = make_windows(grasps, window=4, per_sequence=5)  # last frames 3 .. 7: only the last one slips
    assert windows.labels.reshape(-1, 5).tolist() == [[0, 0, 0, 0, 1]] * len(sequences.labels)
    assert np.array_equal(windows.get(np.arange(5))[1], [0, 0, 0, 0, 1])
    loaded = load_sequences(save_sequences(tmp_path / "grasps", grasps))
    assert np.array_equal(loaded.frame_labels, grasps.frame_labels)
    assert load_sequences(save_sequences(tmp_path / "plain", sequences)).frame_labels is None
    assert np.array_equal(sequences.per_frame_labels()[:, 0], sequences.labels)
    with pytest.raises(ValueError, match=r"frame_labels must have shape \(40, 15\)"):
        SequenceSet(sequences.fields, sequences.labels, sequences.object_ids, {}, grasps.frame_labels[:, :3])
    with pytest.raises(ValueError, match="frame_labels must be 0"):
        SequenceSet(sequences.fields, sequences.labels, sequences.object_ids, {}, grasps.frame_labels * 2)


@pytest.mark.parametrize("kind", ["sequence", "object"])
def test_extra_sequences_only_add_training_windows(sequences: SequenceSet, kind: str) -> None:
    split = split_windows(make_windows(sequences, window=4, per_sequence=5), kind, 0.25, seed=1)
    extra = _grasp_like(synthetic_sequences(6, SMALL, seed=9))
    joined = with_extra_training(split, extra)
    assert np.array_equal(joined.test, split.test) and joined.kind == kind
    assert np.array_equal(joined.train[:split.train.size], split.train)
    added = joined.train[split.train.size:]
    assert np.all(joined.windows.sequence[added] >= 40)  # the extra sequences' windows, after the own ones
    for rows in (split.train, split.test):  # the own windows keep their rows and labels
        assert np.array_equal(joined.windows.labels[rows], split.windows.labels[rows])
        assert np.array_equal(joined.windows.get(rows[:3])[0], split.windows.get(rows[:3])[0])
    assert set(joined.windows.labels[added].tolist()) == {0, 1}  # labelled by their last frame
    test_objects = set(split.windows.object_ids[split.test].tolist())
    extra_objects = joined.windows.object_ids[len(split.windows):]
    if kind == "object":  # no extra window of a test object is trained on
        assert not test_objects & set(joined.windows.object_ids[added].tolist())
        assert 0 < added.size == np.count_nonzero(~np.isin(extra_objects, list(test_objects))) < 30
    else:
        assert added.size == 30
    with pytest.raises(ValueError, match="do not join"):
        with_extra_training(split, synthetic_sequences(4, SyntheticConfig(n_frames=12, grid=12), seed=1))
