"""The simulated slip dataset (fv_algos.sim_dataset): protocol, labels, determinism, bad input."""
from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from fv_algos.sim.objects import SHAPES
from fv_algos.sim.scene import NON_SLIP_KINDS, SLIP_KINDS
from fv_algos.sim_dataset import (GRASP_SEGMENT_STEP, OBJECT_NAMES, SLIP_FROM_FRAME, SimDatasetConfig, generate, iter_sequences, kind_plan,
                                  simulate_grasp, simulate_sequence)
from fv_algos.slip.windows import SequenceSet, load_sequences, make_windows, save_sequences

CONFIG = SimDatasetConfig(n_sequences=12, seed=5)


@pytest.fixture(scope="module")
def dataset() -> SequenceSet:
    return generate(CONFIG, workers=2, progress=False)


def test_shapes_dtypes_and_balance(dataset: SequenceSet) -> None:
    assert dataset.fields.shape == (12, 15, 30, 30, 3)
    assert dataset.fields.dtype == np.float16
    assert np.isfinite(dataset.fields).all()
    assert dataset.labels.tolist().count(1) == 6
    assert Counter(dataset.metadata["kinds"]) == {kind: 2 for kind in SLIP_KINDS + NON_SLIP_KINDS}
    assert set(dataset.object_ids.tolist()) <= set(range(len(SHAPES)))
    assert dataset.metadata["object_names"] == list(OBJECT_NAMES)
    assert dataset.frame_width_px == 640  # the simulated camera's frames, the px of the fields
    assert [len(f) for f in dataset.metadata["frame_slip"]] == [15] * 12


def test_labels_and_objects_follow_the_scenario_kinds(dataset: SequenceSet) -> None:
    kinds = dataset.metadata["kinds"]
    assert dataset.labels.tolist() == [int(k in SLIP_KINDS) for k in kinds]
    for kind, obj, frame_slip in zip(kinds, dataset.object_ids, dataset.metadata["frame_slip"]):
        shape = SHAPES[OBJECT_NAMES[obj]]
        if kind == "rotational":
            assert not shape.AXISYMMETRIC
        if kind == "incipient":
            assert not shape.FLAT
        if kind in NON_SLIP_KINDS:
            assert not any(frame_slip), kind
        else:  # every 10-frame window of a slip sequence contains slipping frames
            assert any(frame_slip[:10]) and all(frame_slip[-5:]), (kind, frame_slip)


def test_fields_show_the_contact_from_a_rest_reference(dataset: SequenceSet) -> None:
    peak = np.abs(dataset.fields[..., 2].astype(np.float32)).max(axis=(1, 2, 3))
    assert (peak > 0.3).all(), peak  # every scenario loads the skin visibly (px)
    assert (peak < 50.0).all(), peak


def test_sequences_depend_only_on_seed_and_index(dataset: SequenceSet) -> None:
    kinds = dataset.metadata["kinds"]
    for index in (0, 7):  # computed in a worker process for the dataset, here in-process
        again = simulate_sequence(CONFIG, index, kinds[index])
        np.testing.assert_array_equal(again.fields.astype(np.float16), dataset.fields[index])
        assert again.object_id == dataset.object_ids[index]
    assert kind_plan(12, 5) == kinds
    assert kind_plan(12, 6) != kinds


def test_save_load_round_trip(dataset: SequenceSet, tmp_path) -> None:
    loaded = load_sequences(save_sequences(tmp_path / "sim", dataset))
    np.testing.assert_array_equal(loaded.fields, dataset.fields)
    assert loaded.metadata["config"]["seed"] == 5
    assert loaded.metadata["kinds"] == dataset.metadata["kinds"]


def test_grasps_are_cut_into_sequences_labelled_frame_by_frame() -> None:
    """Whole grasps (pressed from rest, a scenario, released): sequences every GRASP_SEGMENT_STEP frames,
    per-frame truth as frame_labels, so that windows across a change of the truth carry its last frame's."""
    config = SimDatasetConfig(n_sequences=6, seed=1, grasps=True)
    grasps = generate(config, workers=2, progress=False)
    assert grasps.frame_labels is not None and grasps.frame_labels.shape == grasps.fields.shape[:2]
    assert np.array_equal(grasps.labels, grasps.frame_labels.any(axis=1))
    assert grasps.metadata["frame_slip"] == grasps.frame_labels.tolist()
    first = simulate_grasp(config, 0, kind_plan(6, 1)[0])  # in-process: the worker's sequences again
    assert len(first) >= 3 and all(s.fields.shape == (15, 30, 30, 3) for s in first)
    np.testing.assert_array_equal(first[0].fields.astype(np.float16), grasps.fields[0])
    np.testing.assert_array_equal(first[1].fields[:15 - GRASP_SEGMENT_STEP], first[0].fields[GRASP_SEGMENT_STEP:])
    rest = np.abs(grasps.fields[0, 0].astype(np.float32)).max()
    assert rest < 0.3  # a grasp starts from the skin at rest
    slipping = [k for k, kind in enumerate(grasps.metadata["kinds"]) if kind in SLIP_KINDS]
    assert slipping and any(0 < grasps.frame_labels[k].sum() < 15 for k in slipping)  # the truth changes within
    labels = make_windows(grasps, 10, 5).labels.reshape(-1, 5)
    assert np.array_equal(labels, grasps.frame_labels[:, 9:14])
    assert not grasps.frame_labels[[k for k in range(len(grasps.labels)) if k not in slipping]].any()


def test_bad_input_is_rejected() -> None:
    with pytest.raises(ValueError, match="n_sequences"):
        SimDatasetConfig(n_sequences=1)
    with pytest.raises(ValueError, match="preset"):
        SimDatasetConfig(preset="nope")
    with pytest.raises(ValueError, match="n_frames"):
        SimDatasetConfig(n_frames=3)
    with pytest.raises(ValueError, match="workers"):
        next(iter_sequences(CONFIG, workers=0))


def test_a_sequence_slips_as_its_label_says() -> None:
    """Sequence 70 of the default set (seed 0) is an "incipient" shear on an edge labelled slip, whose
    slip zone stayed under half the contact: its truth said stick on all 15 frames (24 of the 1,600)."""
    config = SimDatasetConfig(n_sequences=1600)
    kind = kind_plan(config.n_sequences, config.seed)[70]
    sequence = simulate_sequence(config, 70, kind)
    assert kind == "incipient" and sequence.label == 1 and sequence.frame_slip[SLIP_FROM_FRAME:].all()


def test_a_draw_whose_mechanics_stop_is_drawn_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """A scenario the mechanics refuse (e.g. an object slid off the skin) ended the whole generation."""
    import fv_algos.sim_dataset as sim_dataset
    real = sim_dataset.SceneRunner
    calls = []

    def refusing_first(scene, skin, contact):
        calls.append(scene)
        if len(calls) == 1:
            raise ValueError("frame 9 (t = 0.600 s): the object's centre (12.10, 0.00) mm has left the skin")
        return real(scene, skin, contact)
    monkeypatch.setattr(sim_dataset, "SceneRunner", refusing_first)
    scene = sim_dataset._scenario_of_kind(np.random.default_rng([0, 1]), "translational", SimDatasetConfig())
    assert len(calls) == 2 and scene is calls[1] and scene != calls[0]
