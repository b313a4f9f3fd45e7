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


def test_load_errors_are_clear(sequences: SequenceSet, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="not found"):
        load_sequences(tmp_path / "missing.npz")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file at all")
    with pytest.raises(ValueError, match="not a slip dataset"):
        load_sequences(garbage)
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
