"""Trial-level slip model: descriptors, the temporal network, its file and object-held-out
cross-validation (no data needed)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from fv_algos.real_trials import VideoFields
from fv_algos.trial_net import (
    DESCRIPTORS,
    MIRROR_X,
    PER_FRAME,
    SCALE,
    START_FRAMES,
    TrialNet,
    TrialNetConfig,
    _balanced_picks,
    _check_setups,
    _held_prefix,
    _label_cells,
    _start_swap,
    camera_descriptors,
    cross_validate_trials,
    fit_trial_net,
    load_trial_model,
    read_trial_model,
    running_probabilities,
    running_probability,
    save_trial_model,
    stretch_in_time,
    trial_probability,
)


def _fields(frames: int, dx_px: float, width_px: int = 320) -> VideoFields:
    grid = np.zeros((frames, 30, 30, 3), np.float16)
    grid[..., 0] = dx_px
    grid[..., 2] = abs(dx_px)
    return VideoFields(grid, np.ones(frames, bool), np.full(frames, 0.9, np.float32), np.zeros(frames, np.int32),
                       40, 0.0, width_px)


def test_descriptors_closed_form_and_mirroring() -> None:
    series = np.zeros((12, 5), np.float32)
    series[:, 2] = np.r_[np.zeros(3), np.full(9, 2.0)]  # shading 2 above the emptiest frame after 3 frames
    series[:, 3] = 10.0  # imprint 10 grey levels from the reference
    d = dict(zip(DESCRIPTORS, camera_descriptors(series, _fields(12, 2.5)).numpy() * SCALE[:, None]))
    np.testing.assert_allclose(d["contact_above_min"], np.r_[np.zeros(3), np.full(9, 2.0)], atol=1e-6)
    np.testing.assert_allclose(d["shear_x_px"], 2.5)
    np.testing.assert_allclose(d["field_px"], 2.5)
    np.testing.assert_allclose(d["invalid_share"], 0.1, atol=1e-6)
    np.testing.assert_allclose(d["divergence"], 0.0, atol=1e-6)
    np.testing.assert_allclose(d["imprint_change"], 10.0)
    mirrored = dict(zip(DESCRIPTORS, MIRROR_X))  # mirroring left-right flips x shear and curl only
    assert mirrored["shear_x_px"] == -1 and mirrored["curl"] == -1 and sum(MIRROR_X) == len(DESCRIPTORS) - 4
    with pytest.raises(ValueError, match="12 contact-series frames but 11 fields"):
        camera_descriptors(series, _fields(11, 1.0))
    # a camera of twice the resolution sees the same shear as twice the px: the same descriptors
    np.testing.assert_array_equal(camera_descriptors(series, _fields(12, 5.0, width_px=640)),
                                  camera_descriptors(series, _fields(12, 2.5)))


def _toy_trials(n: int, seed: int = 0) -> tuple[list[list[torch.Tensor]], np.ndarray]:
    """Slip trials carry a burst of marker motion at a random time, no-slip trials a steady wobble."""
    rng = np.random.default_rng(seed)
    inputs, labels = [], np.arange(n) % 2
    for label in labels:
        cameras = []
        for _ in range(2):
            length = int(rng.integers(60, 200))
            x = rng.normal(0, 0.05, (len(DESCRIPTORS), length)).astype(np.float32)
            if label:
                start = int(rng.integers(0, length - 8))
                x[1, start:start + 8] += 2.0
            else:
                x[1] += 0.4 * np.abs(np.sin(np.arange(length) / 3.0)).astype(np.float32)
            cameras.append(torch.from_numpy(x))
        inputs.append(cameras)
    return inputs, labels


def test_trial_net_learns_a_burst_whatever_the_length_and_round_trips(tmp_path: Path) -> None:
    torch.set_num_threads(1)
    inputs, labels = _toy_trials(40)
    config = TrialNetConfig(steps=60, reference_frame=7, fps=30.0, seed=1)
    net = fit_trial_net(inputs, labels, config)
    test_inputs, test_labels = _toy_trials(20, seed=5)
    assert ((trial_probability(net, test_inputs) >= 0.5) == test_labels).mean() >= 0.9
    path = save_trial_model(tmp_path / "m.pt", net, config)
    assert read_trial_model(path) is not None
    again, params, reference_frame, fps, stretch = load_trial_model(path)
    np.testing.assert_allclose(trial_probability(again, test_inputs), trial_probability(net, test_inputs), rtol=1e-6)
    assert params.size_px == (80, 60)
    assert (reference_frame, fps, stretch) == (7, 30.0, config.stretch)
    with pytest.raises(ValueError, match="slip and no-slip trials"):
        fit_trial_net(inputs, np.zeros(40, int), config)
    with pytest.raises(ValueError, match="an even batch"):
        TrialNetConfig(batch=3)
    with pytest.raises(ValueError, match="reference_frame >= 0"):
        TrialNetConfig(reference_frame=-1)
    with pytest.raises(ValueError, match="finite fps > 0"):
        TrialNetConfig(fps=0.0)
    with pytest.raises(ValueError, match=r"0 < lr < 3.4e\+37 \(got 1e\+38; AdamW's first step"):
        TrialNetConfig(lr=1e38)  # torch's "value cannot be converted to type float without overflow" at its step
    with pytest.raises(ValueError, match="balance one of setup, label \\(got 'labels'\\)"):
        TrialNetConfig(balance="labels")


def test_batches_draw_every_set_up_of_each_label_alike() -> None:
    """Set-up A holds most held grasps and B most slips (the 150 grasps' two magnifications; C only slips): each
    batch takes half slips, half held grasps, each half spread alike over the set-ups that have that label.
    Without set-ups (or balance "label") a batch draws as before: half of each label from all its trials."""
    labels = np.array([1] * 5 + [0] * 18 + [1] * 15 + [0] * 2 + [1] * 3)
    setups = ["A"] * 23 + ["B"] * 17 + ["C"] * 3
    cells = _label_cells(labels, setups)
    assert [[c.size for c in label_cells] for label_cells in cells] == [[5, 15, 3], [18, 2]]
    rng = np.random.default_rng(0)
    drawn = np.stack([_balanced_picks(cells, 12, rng) for _ in range(300)])  # (batches, 12)
    names = np.asarray(setups)[drawn]
    assert (labels[drawn] == 1).sum(axis=1).tolist() == [6] * 300
    for name in "ABC":
        assert ((names == name) & (labels[drawn] == 1)).sum(axis=1).tolist() == [2] * 300  # 6 slips over 3
    for name in "AB":
        assert ((names == name) & (labels[drawn] == 0)).sum(axis=1).tolist() == [3] * 300  # 6 held over 2
    uneven = np.stack([_balanced_picks(cells, 8, rng) for _ in range(400)])  # 4 held over A, B; 4 slips over A, B, C
    assert set(((np.asarray(setups)[uneven] == "A") & (labels[uneven] == 0)).sum(axis=1)) == {2}
    slips_in_a = ((np.asarray(setups)[uneven] == "A") & (labels[uneven] == 1)).sum(axis=1)
    assert set(slips_in_a) == {1, 2} and 0.25 < (slips_in_a == 2).mean() < 0.42  # 4 over 3: one more at random
    old, new = np.random.default_rng(5), np.random.default_rng(5)
    for _ in range(20):
        before = np.concatenate([old.choice(np.flatnonzero(labels == 1), 4), old.choice(np.flatnonzero(labels == 0), 4)])
        np.testing.assert_array_equal(_balanced_picks(_label_cells(labels, None), 8, new), before)
    with pytest.raises(ValueError, match="3 set-ups given for 43 trials"):
        _check_setups(["A", "B", "C"], 43)


def test_balance_label_trains_on_the_batches_without_set_ups() -> None:
    torch.set_num_threads(1)
    inputs, labels = _toy_trials(12)
    config = TrialNetConfig(steps=3, members=1, hidden=4, seed=1)
    setups = ["A"] * 6 + ["B"] * 6  # each with both labels
    by_label = fit_trial_net(inputs, labels, replace(config, balance="label"), setups=setups).state_dict()
    for same in (fit_trial_net(inputs, labels, config).state_dict(),  # no set-ups: one
                 fit_trial_net(inputs, labels, replace(config, balance="label")).state_dict()):
        for name, weight in by_label.items():
            torch.testing.assert_close(same[name], weight, atol=0, rtol=0)
    by_setup = fit_trial_net(inputs, labels, config, setups=setups).state_dict()
    assert any(not torch.equal(by_setup[name], weight) for name, weight in by_label.items())
    for balance in ("setup", "label"):  # set-ups of another length are refused, whether used or not
        with pytest.raises(ValueError, match="13 set-ups given for 12 trials"):
            fit_trial_net(inputs, labels, replace(config, balance=balance), setups=setups + ["A"])
    with pytest.raises(ValueError, match="11 set-ups given for 12 trials"):
        cross_validate_trials(inputs, labels, ["a", "b"] * 6, 2, config=config, setups=setups[:11])



def test_a_network_is_fine_tuned_from_the_one_given_with_the_new_trials_range() -> None:
    """`fv real --init` fine-tuned window models only: a trial network always started from random weights. With
    `init` it starts from that network's weights (one step of a tiny learning rate leaves them), and clamps the
    descriptors to the new trials' range; a network of another shape is refused by name."""
    torch.set_num_threads(1)
    inputs, labels = _toy_trials(20)
    config = TrialNetConfig(steps=30, members=2, hidden=8, seed=1)
    start = fit_trial_net(inputs, labels, config)
    new_inputs, new_labels = _toy_trials(10, seed=3)
    new_inputs = [[3.0 * x for x in cameras] for cameras in new_inputs]  # another sensor's range
    tuned = fit_trial_net(new_inputs, new_labels, replace(config, steps=1, lr=1e-9, seed=2), start)
    scratch = fit_trial_net(new_inputs, new_labels, replace(config, steps=1, lr=1e-9, seed=2))
    for name, weight in start.state_dict().items():
        if name not in ("low", "high"):
            torch.testing.assert_close(tuned.state_dict()[name], weight, atol=1e-6, rtol=0)
            assert not torch.allclose(scratch.state_dict()[name], weight), name
    frames = torch.cat([x for cameras in new_inputs for x in cameras], dim=1)
    torch.testing.assert_close(tuned.high, frames.amax(dim=1))
    assert not torch.allclose(start.high, tuned.high)
    with pytest.raises(ValueError, match="has hidden 8, layers 4, members 2; the training asks for 8, 4, 1"):
        fit_trial_net(new_inputs, new_labels, replace(config, members=1), start)

def test_descriptors_are_clamped_to_the_range_of_the_training_frames() -> None:
    torch.set_num_threads(1)
    inputs, labels = _toy_trials(10)
    net = fit_trial_net(inputs, labels, TrialNetConfig(steps=2, members=1, clip=0.0))
    frames = torch.cat([x for cameras in inputs for x in cameras], dim=1)
    torch.testing.assert_close(net.low, frames.amin(dim=1))
    torch.testing.assert_close(net.high, frames.amax(dim=1))
    far = [[torch.where(x > 0, 1e6, -1e6) for x in inputs[0]]]  # a sensor far out of the training range
    edge = [[torch.where(x > 0, net.high[:, None], net.low[:, None]) for x in inputs[0]]]
    np.testing.assert_allclose(trial_probability(net, far), trial_probability(net, edge), rtol=1e-6)
    quartiles = fit_trial_net(inputs, labels, TrialNetConfig(steps=2, members=1, clip=0.25))
    torch.testing.assert_close(quartiles.high, torch.quantile(frames, 0.75, dim=1))
    with pytest.raises(ValueError, match="0 <= clip < 0.5"):
        TrialNetConfig(clip=0.5)


def test_stretching_in_time_resamples_levels_and_slows_rates() -> None:
    frames = 41
    ramp = np.tile(np.linspace(0.0, 4.0, frames, dtype=np.float32), (len(DESCRIPTORS), 1))  # 0.1 per frame
    slow = stretch_in_time(torch.from_numpy(ramp), 2.0).numpy()
    assert slow.shape == (len(DESCRIPTORS), 82)
    levels, rates = slow[~PER_FRAME], slow[PER_FRAME]
    np.testing.assert_allclose(levels, np.tile(np.linspace(0.0, 4.0, 82), (len(levels), 1)), atol=1e-5)
    np.testing.assert_allclose(rates, levels[:len(rates)] / 2.0, atol=1e-5)  # twice as slow: half per frame
    assert {DESCRIPTORS[i] for i in np.flatnonzero(PER_FRAME)} == {"relative_px", "marker_px", "imprint_step_rms"}
    assert stretch_in_time(torch.from_numpy(ramp), 0.5).shape == (len(DESCRIPTORS), 20)
    assert stretch_in_time(torch.from_numpy(ramp[:, :1]), 0.5).shape == (len(DESCRIPTORS), 2)
    np.testing.assert_array_equal(stretch_in_time(torch.from_numpy(ramp), 1.0).numpy(), ramp)
    with pytest.raises(ValueError, match="stretch >= 1"):
        TrialNetConfig(stretch=0.5)


def test_a_held_prefix_cuts_both_cameras_to_one_beginning_of_ten_frames_or_more() -> None:
    cameras = [torch.arange(11 * 40, dtype=torch.float32).view(11, 40), torch.zeros(11, 42)]
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert _held_prefix(cameras, rng, 0.0) is cameras and rng.bit_generator.state == state  # no draw at 0
    kept = set()
    for _ in range(300):
        cut = _held_prefix(cameras, rng, 1.0)
        assert cut[0].shape[1] == cut[1].shape[1]
        torch.testing.assert_close(cut[0], cameras[0][:, :cut[0].shape[1]])
        kept.add(cut[0].shape[1])
    assert min(kept) == 10 and max(kept) == 40 and len(kept) == 31  # every length of the shorter camera
    short = [torch.zeros(11, 4)]
    assert _held_prefix(short, rng, 1.0)[0].shape == (11, 4)
    cut_share = np.mean([_held_prefix(cameras, rng, 0.3) is not cameras for _ in range(2000)])
    assert 0.25 < cut_share < 0.35
    with pytest.raises(ValueError, match="0 <= held_prefix <= 1"):
        TrialNetConfig(held_prefix=1.5)


def test_a_start_swap_trades_the_first_frames_for_a_donor_camera_of_the_other_label() -> None:
    x = torch.arange(11 * 40, dtype=torch.float32).view(11, 40)
    donors = [[torch.full((11, 30), 1.0), torch.full((11, 30), 2.0)], [torch.full((11, 50), 3.0)]]
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert _start_swap(x, donors, rng, 0.0) is x and rng.bit_generator.state == state  # no draw at 0
    starts = set()
    for _ in range(200):
        swapped = _start_swap(x, donors, rng, 1.0)
        assert swapped.shape == x.shape
        torch.testing.assert_close(swapped[:, START_FRAMES:], x[:, START_FRAMES:])  # the rest is the camera's own
        assert len(set(swapped[:, :START_FRAMES].flatten().tolist())) == 1  # the start is one donor's
        starts.add(swapped[0, 0].item())
    assert starts == {1.0, 2.0, 3.0}  # every camera of every donor trial
    assert _start_swap(x[:, :START_FRAMES], donors, rng, 1.0).shape == (11, START_FRAMES)  # too short: kept
    swap_share = np.mean([_start_swap(x, donors, rng, 0.3) is not x for _ in range(2000)])
    assert 0.25 < swap_share < 0.35
    with pytest.raises(ValueError, match="0 <= start_swap <= 1"):
        TrialNetConfig(start_swap=-0.1)


def test_object_held_out_cross_validation_keeps_objects_apart() -> None:
    torch.set_num_threads(1)
    inputs, labels = _toy_trials(30)
    objects = [f"o{i % 6}" for i in range(30)]
    config = TrialNetConfig(steps=20)  # the toy trials are told apart after 10 steps (40 took twice as long)
    report = cross_validate_trials(inputs, labels, objects, folds=3, config=config, workers=2)
    assert len(report["folds"]) == 3 and report["summary"]["trial_accuracy_mean"] >= 0.8
    for fold in report["folds"]:  # every test object is absent from its fold's training trials
        assert {objects[i] for i in fold["trials"]} == set(fold["objects"])
    assert sum(fold["n_trials"] for fold in report["folds"]) == 30
    assert "running" not in report
    # In this process with the online pass: the same figures as the folds in two spawned processes
    # without it (the processes change no figure, nor does the online pass).
    online = cross_validate_trials(inputs, labels, objects, folds=3, config=config, online=True)
    assert {key: value for key, value in online.items() if key != "running"} == report
    assert [[len(series) for series in cameras] for cameras in online["running"]] == [
        [x.shape[1] for x in cameras] for cameras in inputs]


def test_running_probability_is_the_network_on_every_prefix() -> None:
    torch.manual_seed(0)
    net = TrialNet(4, members=2).eval()
    x = torch.randn(len(DESCRIPTORS), 3 * (2 * net.radius + 1))  # three times the running memory
    offline = [trial_probability(net, [[x[:, :t]]])[0] for t in range(1, x.shape[1] + 1)]
    np.testing.assert_allclose(running_probability(net, x), offline, atol=1e-5)
    inputs = [[x[:, :40], x[:, 5:]], [x[:, :3]], [x]]
    one = running_probabilities(net, inputs)
    assert [[len(series) for series in cameras] for cameras in one] == [[40, x.shape[1] - 5], [3], [x.shape[1]]]
    two = running_probabilities(net, inputs, workers=2)  # the trials split between two spawned processes
    assert all(np.array_equal(a, b) for p, q in zip(one, two) for a, b in zip(p, q))


def test_a_model_file_of_another_kind_is_refused(tmp_path: Path) -> None:
    torch.save({"kind": "something_else"}, tmp_path / "other.pt")
    assert read_trial_model(tmp_path / "other.pt") is None
    with pytest.raises(ValueError, match="not a trial-level slip model"):
        load_trial_model(tmp_path / "other.pt")
    save_trial_model(tmp_path / "m.pt", TrialNet(4), TrialNetConfig(hidden=4, members=1))
    data = torch.load(tmp_path / "m.pt", weights_only=False)
    data["descriptors"] = data["descriptors"][:-1]
    torch.save(data, tmp_path / "old.pt")
    with pytest.raises(ValueError, match="differ from this code.*retrain the model with `fv real train`"):
        load_trial_model(tmp_path / "old.pt")


def test_layers_set_the_context_and_older_files_load_with_the_defaults_of_their_time(tmp_path: Path) -> None:
    assert [TrialNet(4, layers).radius for layers in (1, 3, 4)] == [2, 14, 30]
    net = TrialNet(4, 4)
    for conv in net.temporal[::2]:  # positive weights: every input a frame depends on shows in it
        torch.nn.init.constant_(conv.weight, 0.1)
        torch.nn.init.zeros_(conv.bias)
    with torch.no_grad():
        features = [net.temporal(torch.eye(61)[k].expand(len(DESCRIPTORS), 61)[None])[0, :, 0] for k in (30, 31)]
    assert features[0].min() > 0 and features[1].abs().max() == 0  # frame 0 sees frame 30, not 31
    three = TrialNet(4, 3)
    save_trial_model(tmp_path / "m.pt", three, TrialNetConfig(hidden=4, layers=3, members=1))
    data = torch.load(tmp_path / "m.pt", weights_only=False)
    for key in ("layers", "members", "reference_frame", "fps", "stretch"):
        del data["config"][key]  # as written before they were settings
    torch.save(data, tmp_path / "old.pt")
    again, _, reference_frame, fps, stretch = load_trial_model(tmp_path / "old.pt")
    assert again.radius == 14 and (reference_frame, fps, stretch) == (1, 25.0, 1.0)
    inputs, _ = _toy_trials(4)
    np.testing.assert_allclose(trial_probability(again, inputs), trial_probability(three, inputs), rtol=1e-6)
    with pytest.raises(ValueError, match="layers"):
        TrialNetConfig(layers=0)


def _member(net: TrialNet, m: int) -> TrialNet:
    """Member ``m`` of ``net`` as a one-member network with the same weights."""
    one = TrialNet(net.hidden, net.layers)
    own = slice(m * net.hidden, (m + 1) * net.hidden)
    with torch.no_grad():
        for k, (conv, mine) in enumerate(zip(net.temporal[::2], one.temporal[::2])):
            mine.weight.copy_(conv.weight[own])  # grouped after the first: the inputs are the member's own
            mine.bias.copy_(conv.bias[own])
        one.head.weight.copy_(net.head.weight[m:m + 1])
        one.head.bias.copy_(net.head.bias[m:m + 1])
    return one.eval()


def test_an_ensemble_is_the_mean_of_independent_members(tmp_path: Path) -> None:
    torch.manual_seed(0)
    net = TrialNet(4, 2, members=3).eval()
    inputs, _ = _toy_trials(6)
    with torch.no_grad():
        whole = torch.stack([net(x) for x in inputs])
        members = torch.stack([torch.stack([_member(net, m)(x) for x in inputs]) for m in range(3)])
    torch.testing.assert_close(whole, members.mean(dim=0), rtol=1e-5, atol=1e-6)
    net.member_logits(net.pooled(inputs[0]))[1].backward()  # member 1's logit moves member 1's weights only
    own = torch.arange(12) // 4 == 1
    for conv in net.temporal[::2]:
        assert conv.weight.grad[~own].abs().max() == 0 and conv.weight.grad[own].abs().max() > 0
    assert net.head.weight.grad[[0, 2]].abs().max() == 0 and net.head.bias.grad[[0, 2]].abs().max() == 0
    save_trial_model(tmp_path / "m.pt", net, TrialNetConfig(hidden=4, layers=2, members=3))
    again = load_trial_model(tmp_path / "m.pt").net
    np.testing.assert_allclose(trial_probability(again, inputs), torch.sigmoid(whole).numpy(), rtol=1e-6)
    with pytest.raises(ValueError, match="members 3 saved with"):
        save_trial_model(tmp_path / "m.pt", net, TrialNetConfig(hidden=4, layers=2, members=1))
    with pytest.raises(ValueError, match="members"):
        TrialNetConfig(members=0)
