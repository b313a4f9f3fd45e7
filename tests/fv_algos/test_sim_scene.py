"""Scene descriptions, actions and random scenarios."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from fv_algos.sim.contact import ContactParams
from fv_algos.sim.scene import (MAX_SLIDE_MM, NON_SLIP_KINDS, SLIP_KINDS, Loads, grasp_scene, load_scene, noisy_labels, random_scenario,
                                scene_commands, scene_from_dict)
from fv_algos.sim.sensor import SceneRunner
from fv_algos.sim.skin import SkinParams
from fv_algos.yaml_loader import YamlLoader

EXAMPLE = {
    "object": {"shape": "sphere", "radius_mm": 10, "mu": 0.8},
    "fps": 20,
    "effects": ["normal", "shear", "slip", "noise"],
    "steps": [
        {"action": "press", "duration_s": 0.5, "normal_N": 2.0},
        {"action": "shear", "duration_s": 0.5, "force_N": [0.8, 0]},
        {"action": "slide", "duration_s": 0.5, "velocity_mm_s": [4, 0]},
        {"action": "release", "duration_s": 0.5},
    ],
}


def _run(desc: dict) -> list:
    return list(SceneRunner(scene_from_dict(desc), SkinParams(), ContactParams()))


def test_actions_do_what_they_say() -> None:
    frames = _run(EXAMPLE)
    assert len(frames) == 40
    normal = [f.state.normal_N for f in frames[:10]]
    assert np.all(np.diff(normal) > 0)  # press raises the normal load
    shear = frames[19].state
    assert shear.force_N[0] == pytest.approx(0.8 * 9 / 10, rel=0.01) and shear.slip_state != "gross"
    sliding = frames[21:30]
    assert all(f.state.slip_state == "gross" and f.state.slip_type == "translational" for f in sliding)
    centres = np.array([f.centre_mm[0] for f in sliding])
    np.testing.assert_allclose(np.diff(centres), 4.0 / 20)  # the object slides 4 mm/s
    x = frames[0].state.displacement_mm  # contact patch moves with it
    patch_x = [np.mean(np.meshgrid(*(2 * [np.arange(64)]))[0][f.state.contact]) for f in (sliding[0], sliding[-1])]
    assert patch_x[1] - patch_x[0] == pytest.approx((centres[-1] - centres[0]) / (24 / 64), abs=1.0)
    assert not np.any(x)  # t = 0: nothing pressed yet
    release = _run({**EXAMPLE, "steps": EXAMPLE["steps"] + [{"action": "hold", "duration_s": 0.1}]})[-1]
    assert release.state.normal_N == 0 and not np.any(release.state.displacement_mm)


def test_twist_and_roll() -> None:
    desc = {"object": {"shape": "key"}, "fps": 10, "initial": {"normal_N": 2.0},
            "steps": [{"action": "twist", "duration_s": 0.5, "angular_velocity_deg_s": 40}, {"action": "roll", "duration_s": 0.5, "velocity_mm_s": [0, 2]}]}
    frames = _run(desc)
    assert scene_from_dict(desc).effects == {"normal", "torsion", "slip"}
    assert all(f.state.slip_type == "rotational" and f.state.slip_state == "gross" for f in frames[:5])
    assert frames[5].angle_rad == pytest.approx(np.radians(40 * 0.5))
    rolling = frames[6:]
    assert all(f.state.slip_state == "stick" and not np.any(f.state.traction_mpa) for f in rolling)
    assert rolling[-1].centre_mm[1] - rolling[0].centre_mm[1] == pytest.approx(2 * 0.3)


@pytest.mark.parametrize(
    "change, key",
    [
        ({"fps": -1}, "fps"),
        ({"object": {"shape": "banana"}}, "shape"),
        ({"object": {"shape": "sphere", "radius": 3}}, "radius"),
        ({"steps": [{"action": "press", "duration_s": 1}]}, "normal_N"),
        ({"steps": [{"action": "jump", "duration_s": 1}]}, "action"),
        ({"steps": [{"action": "shear", "duration_s": 1, "force_N": [1]}]}, "force_N"),
        ({"steps": [{"action": "hold", "duration_s": 0}]}, "duration_s"),
        ({"effects": ["normal"]}, "effects"),
        ({"colour": "red"}, "colour"),
        ({"steps": [{"action": "press", "duration_s": 1, "normal_N": 1, "torque_Nmm": 2}]}, "torque_Nmm"),
        ({"steps": [{"action": "slide", "duration_s": 1, "velocity_mm_s": [0, 0]}]}, "a slide at zero speed"),
        ({"steps": [{"action": "twist", "duration_s": 1, "angular_velocity_deg_s": 0}]}, "a twist at zero speed"),
        ({"slide_speed_mm_s": -5}, "slide_speed_mm_s must be > 0"),  # moved the object against the force
        ({"spin_rate_deg_s": 0}, "spin_rate_deg_s must be > 0"),      # gross slip that never moved
        ({"effects": ["normal", {"x": 1}]}, "effects must be a list of names"),  # unhashable type: 'dict'
        ({"effects": ["normal", "shear", "normal"]}, r"effects lists \['normal'\] more than once"),  # taken as one
        ({"object": {"shape": "sphere", "radius_mm": "10"}}, "object.radius_mm: '10' is not a finite number"),  # taken
        # a TypeError (unhashable type: 'list') from deep inside, not a ValueError naming the key:
        ({"object": {"shape": ["sphere"]}}, r"object.shape must be one of \['bottle_cap', .*\] \(got \['sphere'\]\)"),
        ({"steps": [{"action": ["hold"], "duration_s": 1}]}, r"steps\[0\].action must be one of .*, got \['hold'\]"),
        # 400 digits, as YAML and JSON read them: an OverflowError, and for fps a TypeError from np.isfinite
        ({"object": {"shape": "sphere", "radius_mm": 10**400}}, "object.radius_mm: an integer past the float range .* is not a finite number"),
        ({"fps": 10**400}, "fps: an integer past the float range .* is not a finite number"),
        ({"initial": {"force_N": [10**400, 0]}}, "initial.force_N: an integer past the float range"),
        ({"fps": float("nan")}, "fps: nan is not a finite number"),
        ({"object": {"shape": "edge", "wedge_angle_deg": 180}}, r"Edge.wedge_angle_deg must be in \(0, 180\) deg, exclusive, got 180"),
        ({"object": {"shape": "edge", "wedge_angle_deg": 270}}, r"wedge_angle_deg must be in \(0, 180\)"),  # contact on the rims
        ({"object": {"shape": "edge", "wedge_angle_deg": 0}}, "wedge_angle_deg must be finite and > 0"),
    ],
)
def test_bad_descriptions_name_the_key(change: dict, key: str) -> None:
    with pytest.raises(ValueError, match=key):
        scene_from_dict({**EXAMPLE, **change})


def test_mechanics_a_scene_cannot_play_are_named_by_frame() -> None:
    off = {**EXAMPLE, "steps": [{"action": "press", "duration_s": 0.2, "normal_N": 2.0},
                                {"action": "slide", "duration_s": 4.0, "velocity_mm_s": [5, 0]}]}
    with pytest.raises(ValueError, match=r"frame 5\d \(t = 2.6\d0 s\): the object's centre \(12.\d\d, 0.00\) mm has "
                                         r"left the skin, which spans \+-12 mm"):  # its whole load pressed the rim
        _run(off)
    past = {"object": {"shape": "sphere", "mu": 0.5}, "fps": 10, "effects": ["normal", "shear"],
            "initial": {"normal_N": 2.0}, "steps": [{"action": "shear", "duration_s": 1.0, "force_N": [2.0, 0]}]}
    with pytest.raises(ValueError, match="frame 5 .* pass the friction limit .* lacks the 'slip' effect"):
        _run(past)  # the truth said gross slip while the object stood still
    assert _run({**past, "effects": ["normal", "shear", "slip"]})[-1].centre_mm[0] > 0


def test_a_scene_with_a_load_past_the_solver_range_is_refused_by_name(tmp_path) -> None:
    """A sphere pressed off the skin's centre with 1e200 N hung the contact solver."""
    (tmp_path / "s.yaml").write_text("object: {shape: sphere, radius_mm: 10}\nfps: 30\ninitial: {normal_N: 1.0e+200}\n"
                                     "steps: [{action: hold, duration_s: 0.1}]\n")
    with pytest.raises(ValueError, match=r"load_N 1e\+200 N"):
        list(SceneRunner(load_scene(tmp_path / "s.yaml"), SkinParams(), ContactParams()))


def test_a_shear_with_no_normal_load_is_past_the_friction_limit() -> None:
    """It was 'stick' in every frame, the shear dropped (nothing pressed: zero contact, zero traction)."""
    unpressed = {"object": {"shape": "sphere"}, "fps": 10, "steps": [{"action": "shear", "duration_s": 0.5, "force_N": [1, 0]}]}
    with pytest.raises(ValueError, match=r"frame 1 \(t = 0.100 s\): the loads pass the friction limit \(gross "
                                         r"translational slip\) but the scene lacks the 'slip' effect"):
        _run(unpressed)
    frames = _run({**unpressed, "effects": ["normal", "shear", "slip"], "slide_speed_mm_s": 4.0})
    assert frames[0].state.slip_state == "stick"  # no load yet
    assert all(f.state.slip_state == "gross" and f.state.slip_type == "translational" for f in frames[1:])
    np.testing.assert_allclose([f.centre_mm for f in frames], [[0.4 * max(k - 1, 0), 0.0] for k in range(5)], atol=1e-12)
    assert not any(f.state.contact.any() or f.state.force_N.any() for f in frames)  # nothing carried the shear
    twist = {"object": {"shape": "key"}, "fps": 10, "steps": [{"action": "twist", "duration_s": 0.3, "torque_Nmm": 2.0}]}
    with pytest.raises(ValueError, match="frame 1 .* pass the friction limit \\(gross rotational slip\\)"):
        _run(twist)
    still = _run({"object": {"shape": "sphere"}, "fps": 10, "effects": ["normal", "shear"],
                  "steps": [{"action": "hold", "duration_s": 0.3}, {"action": "release", "duration_s": 0.2}]})
    assert all(f.state.slip_state == "stick" for f in still)  # no shear, no normal load: fine


def test_yaml_and_json_files(tmp_path) -> None:
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(EXAMPLE))
    (tmp_path / "s.json").write_text(json.dumps(EXAMPLE))
    assert load_scene(tmp_path / "s.yaml") == load_scene(tmp_path / "s.json") == scene_from_dict(EXAMPLE)
    with pytest.raises(ValueError, match="yaml"):
        load_scene(tmp_path / "s.txt")
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(EXAMPLE).replace("duration_s: 0.5", "duration_s: 5e-1"))
    assert load_scene(tmp_path / "e.yaml") == scene_from_dict(EXAMPLE)  # YAML 1.2's 5e-1 is a number
    (tmp_path / "broken.yaml").write_text("object: {shape: sphere\nfps: 30\n")
    with pytest.raises(ValueError, match=r"broken.yaml: not YAML: line 2, column 4: expected ',' or '}'"):
        load_scene(tmp_path / "broken.yaml")  # a parser traceback naming "<unicode string>"
    (tmp_path / "bad.json").write_text(json.dumps({**EXAMPLE, "object": {"shape": "egg"}}))
    with pytest.raises(ValueError, match=r"bad.json: .*object.shape must be one of \[.*\] \(got 'egg'\)"):
        load_scene(tmp_path / "bad.json")
    (tmp_path / "huge.json").write_text(json.dumps({**EXAMPLE, "object": {"shape": "sphere", "radius_mm": 10**400}}))
    with pytest.raises(ValueError, match="huge.json: object.radius_mm: an integer past the float range"):
        load_scene(tmp_path / "huge.json")  # OverflowError: int too large to convert to float


@pytest.mark.parametrize(
    "text, line, column, key",
    [  # the last one won: a press of 50 N, and fps 10
        ("object: {shape: sphere}\nfps: 10\nsteps:\n  - {action: press, duration_s: 0.2, normal_N: 2.0, normal_N: 50.0}\n",
         4, 53, "normal_N"),
        ("object: {shape: sphere}\nfps: 30\nsteps: [{action: hold, duration_s: 0.1}]\nfps: 10\n", 4, 1, "fps"),
    ],
)
def test_a_repeated_key_is_refused_with_its_line(tmp_path, text: str, line: int, column: int, key: str) -> None:
    (tmp_path / "dup.yaml").write_text(text)
    with pytest.raises(ValueError, match=rf"dup.yaml: not YAML: line {line}, column {column}: found duplicate key '{key}'"):
        load_scene(tmp_path / "dup.yaml")


def test_a_merge_may_still_override_a_key() -> None:
    text = "base: &b {shape: sphere, radius_mm: 5}\nobject: {<<: *b, radius_mm: 8}\n"
    assert yaml.load(text, Loader=YamlLoader)["object"] == {"shape": "sphere", "radius_mm": 8}


@pytest.mark.parametrize("text, value", [("1e9", 1e9), ("-2E-3", -2e-3), ("1.0e12", 1e12), ("1.5e3", 1500.0),
                                         (".5e1", 5.0), ("1.0e+12", 1e12), ("3.0", 3.0), ("1e", "1e"), ("e5", "e5")])
def test_numbers_are_read_as_yaml_1_2_writes_them(text: str, value: object) -> None:
    """PyYAML (YAML 1.1) reads 1.0e12 and 1.5e3 as text: a scene's `mu: 1.0e12` was "not a finite number"."""
    assert yaml.load(f"x: {text}", Loader=YamlLoader)["x"] == value


@pytest.mark.parametrize("kind", SLIP_KINDS + NON_SLIP_KINDS)
def test_random_scenarios_have_the_labels_they_claim(kind: str) -> None:
    rng = np.random.default_rng(11)
    for _ in range(3):
        scene = random_scenario(rng, kind)
        frames = list(SceneRunner(scene, SkinParams(), ContactParams()))
        assert len(frames) == 15 and scene.fps == 15
        labels = np.array([f.state.is_slip for f in frames])
        if kind in SLIP_KINDS:
            # Every 10-frame window contains slip of the claimed kind.
            assert all(labels[k:k + 10].any() for k in range(6)), (kind, scene.obj, labels)
            claimed = "translational" if kind == "incipient" else kind
            assert all(f.state.slip_type == claimed for f in frames if f.state.is_slip)
            if kind == "incipient":
                assert all(f.state.slip_state == "incipient" for f in frames)
        else:
            assert not labels.any(), (kind, scene.obj, [f.state.slip_share for f in frames])


def _slide(scene) -> tuple[float, np.ndarray]:
    """(speed mm/s, end of the object's centre (2,) mm) of a translational scenario's slide."""
    (slide,) = [step for step in scene.steps if step.action == "slide"]
    velocity = np.array(slide.velocity_mm_s)
    return float(np.hypot(*velocity)), np.array(scene.start_mm) + velocity * slide.duration_s


def test_a_slide_keeps_the_object_on_the_skin() -> None:
    """The data set's 1 s slides keep their drawn speed (3 to 8 mm/s); the main job's 4 s motions at
    15 fps (60 frames) slide slower, at most MAX_SLIDE_MM, so the object's centre stays on the 24 mm skin:
    before, such slides ended 14 to 26 mm from the centre, where the whole load pressed on the sliver of
    the object left over the skin."""
    short = [_slide(random_scenario(np.random.default_rng(seed), "translational")) for seed in range(40)]
    speeds = [speed for speed, _ in short]
    assert min(speeds) >= 3.0 and max(speeds) > 7.5  # as drawn: the cap does not touch them
    for seed in range(40):
        scene = random_scenario(np.random.default_rng(seed), "translational", n_frames=60, fps=15.0)
        speed, end = _slide(scene)
        (slide,) = [step for step in scene.steps if step.action == "slide"]
        assert speed * slide.duration_s <= MAX_SLIDE_MM + 1e-9
        assert np.abs(end).max() < SkinParams().size_mm / 2


@pytest.mark.parametrize("fps", [0.5, 1e-3])
def test_a_random_slide_at_a_low_frame_rate_keeps_the_object_on_the_skin(fps: float) -> None:
    """The shear ramp of a random slide lasts 1 to 3 frames, its loads past the friction limit slipping the object
    at the scene's slide speed (5 mm/s): at 0.5 fps 2 to 6 s, 10 to 30 mm. The camera's random scenarios at
    fps:=0.5 slid 28 of 40 slides off the skin ('... has left the skin; reopening'). The ramp's slip is now at
    most MAX_RAMP_SLIP_MM; at 15 fps and more the slides are as drawn (the data set's)."""
    rng = np.random.default_rng(1)
    for _ in range(8):
        scene = grasp_scene(random_scenario(rng, "translational", n_frames=60, fps=fps))
        frames = list(SceneRunner(scene, SkinParams(), ContactParams()))  # ValueError: the object left the skin
        assert any(f.state.slip_state == "gross" for f in frames)
    for rate in (15.0, 30.0):
        assert random_scenario(np.random.default_rng(1), "translational", 60, rate).slide_speed_mm_s == 5.0


def _numbers(loads: Loads) -> list[float]:
    return [loads.normal_N, *loads.force_N, loads.torque_Nmm]


@pytest.mark.parametrize("kind", ["translational", "incipient", "rotational", "pressing"])
def test_a_grasp_starts_and_ends_at_rest_and_plays_its_scenario_between(kind: str) -> None:
    scene = random_scenario(np.random.default_rng(5), kind, n_frames=15, fps=30.0)
    grasp = grasp_scene(scene, approach_s=0.4, release_s=0.4, rest_s=0.2)
    commands = list(scene_commands(grasp))
    assert grasp.initial == Loads() and commands[0].loads == Loads()
    approach = 12 + 6 * (any(scene.initial.force_N))  # frames of the press (0.4 s) and the shear (0.2 s)
    body = list(scene_commands(scene))
    assert {c.action for c in commands[approach + 1:approach + 15]} == {c.action for c in body[1:]}  # (a frame
    # on a step's boundary, the body's first one included, may fall on either side of it: the times are sums of floats)
    np.testing.assert_allclose([_numbers(c.loads) for c in commands[approach:approach + 15]],
                               [_numbers(c.loads) for c in body], atol=1e-9)
    assert [c.action for c in commands[approach + 15:]] == ["release"] * 12 + ["hold"] * 6
    assert commands[-1].loads == Loads()
    frames = list(SceneRunner(grasp, SkinParams(), ContactParams()))
    for rest in (frames[0], frames[-1]):  # no load, no contact, the skin undeformed
        assert not rest.state.contact.any() and not rest.state.is_slip
        assert np.abs(rest.state.displacement_mm).max() < 1e-9
    with pytest.raises(ValueError, match="approach_s, release_s and rest_s must be > 0"):
        grasp_scene(scene, approach_s=0.0)


def test_noisy_labels() -> None:
    labels = np.array([0] * 6 + [1] * 9, dtype=bool)
    rng = np.random.default_rng(0)
    assert np.array_equal(noisy_labels(labels, rng), labels)
    assert np.array_equal(noisy_labels(labels, rng, flip_probability=1.0), ~labels)
    shifted = noisy_labels(labels, rng, max_onset_shift_frames=3)
    assert abs(int(np.argmax(shifted)) - 6) <= 3 and shifted[-1]
    with pytest.raises(ValueError, match="flip_probability"):
        noisy_labels(labels, rng, flip_probability=2.0)


@pytest.mark.parametrize("fps, duration_s, frames", [
    (5, 0.5, 3), (5, 0.7, 4), (5, 0.9, 5),  # round() made them 2, 4 and 4 (halves to even)
    (5, 1.0, 5), (30, 2.9, 87), (30, 1.7, 51),  # 1.7 * 30 = 51.00000000000001: still 51
    (10, 0.1 + 0.2, 3), (15, 5.1, 77), (1, 1e-6, 1),
])
def test_a_scene_has_a_frame_at_each_multiple_of_the_frame_period_before_its_end(fps: float, duration_s: float,
                                                                                  frames: int) -> None:
    scene = scene_from_dict({"object": {"shape": "sphere"}, "fps": fps, "initial": {"normal_N": 1.0},
                             "steps": [{"action": "hold", "duration_s": duration_s}]})
    assert scene.n_frames == frames
    stamps = [c.stamp_s for c in scene_commands(scene)]
    assert stamps[-1] < duration_s <= stamps[-1] + 1.0 / fps + 1e-12


@pytest.mark.parametrize("change, message", [
    ({"steps": [{"action": "press", "duration_s": 1e308, "normal_N": 1}]},  # OverflowError: cannot convert float infinity
     r"^steps\[0\].duration_s 1e\+308 s at 20 fps is over 1e308 frames; a scene has at most 100,000 frames \(5000 s at 20 fps\)$"),
    ({"steps": [{"action": "press", "duration_s": 0.5, "normal_N": 1}, {"action": "hold", "duration_s": 6000}]},
     r"^steps\[1\].duration_s 6000 s at 20 fps is 1.2e\+05 frames; a scene has at most 100,000"),
    ({"steps": [{"action": "hold", "duration_s": 4000}, {"action": "hold", "duration_s": 4000}]},
     r"^the steps last 8000 s in all, 1.6e\+05 frames at 20 fps; a scene has at most 100,000"),
    ({"fps": 1e12}, r"^steps\[0\].duration_s 0.5 s at 1e\+12 fps is 5e\+11 frames; .* \(1e-07 s at 1e\+12 fps\)$"),
])
def test_a_scene_of_more_frames_than_a_count_can_be_is_refused_naming_the_step(change: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        scene_from_dict({**EXAMPLE, **change})


def test_a_huge_duration_is_an_error_of_fv_sim_not_a_traceback(tmp_path, capsys) -> None:
    from nodes.cli import main
    (tmp_path / "long.yaml").write_text("object: {shape: sphere}\nfps: 30\n"
                                        "steps: [{action: press, duration_s: 1e308, normal_N: 1}]\n")
    assert main(["sim", "--scene", str(tmp_path / "long.yaml"), "--preview", str(tmp_path / "p.png")]) == 2
    assert "long.yaml: steps[0].duration_s 1e+308 s at 30 fps is over 1e308 frames" in capsys.readouterr().err


def test_a_position_far_off_the_skin_is_named_in_few_digits() -> None:
    """A slide at 1e300 mm/s printed the object's centre in 300 digits."""
    fast = {**EXAMPLE, "steps": [{"action": "press", "duration_s": 0.1, "normal_N": 1},
                                 {"action": "slide", "duration_s": 0.1, "velocity_mm_s": [1e300, 0]}]}
    with pytest.raises(ValueError, match=r"^frame 3 \(t = 0.150 s\): the object's centre \(5e\+298, 0.00\) mm has left"):
        _run(fast)


@pytest.mark.parametrize("name", ["latin1.yaml", "latin1.json"])
def test_a_scene_file_that_is_not_utf8_is_named_with_its_line(tmp_path, name: str) -> None:
    """It said only "'utf-8' codec can't decode byte 0xe9 in position 38: invalid continuation byte"."""
    text = "# sc\u00e8ne\n" if name.endswith(".yaml") else ""
    (tmp_path / name).write_bytes((text + json.dumps(EXAMPLE)).encode("latin-1") if text
                                  else json.dumps({**EXAMPLE, "note": "\u00e9"}, ensure_ascii=False).encode("latin-1"))
    with pytest.raises(ValueError, match=rf"^{tmp_path / name} line 1: not UTF-8 text \(invalid continuation byte, "
                                         r"byte 0xe[89]\): save it as UTF-8$"):
        load_scene(tmp_path / name)
    (tmp_path / "bom.json").write_bytes(b"\xef\xbb\xbf" + json.dumps(EXAMPLE).encode())
    assert load_scene(tmp_path / "bom.json") == scene_from_dict(EXAMPLE)  # as an editor on Windows may save it: it
    # was "not JSON: Unexpected UTF-8 BOM"
