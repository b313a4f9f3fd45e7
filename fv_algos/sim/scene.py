"""Scripted contact scenes and random slip / no-slip scenarios.

A scene is an object, a frame rate, the effects it uses and a list of timed steps, played as frames at
t = k / fps for every t before the end of its last step (`Scene.n_frames`: 0.5 s at 5 fps is 3 frames):

    {"object": {"shape": "sphere", "radius_mm": 10, "mu": 0.8}, "fps": 60,
     "effects": ["normal", "shear", "slip"],
     "steps": [{"action": "press", "duration_s": 0.5, "normal_N": 2.0},
               {"action": "shear", "duration_s": 0.5, "force_N": [0.8, 0]},
               {"action": "slide", "duration_s": 1.0, "velocity_mm_s": [3, 0]},
               {"action": "release", "duration_s": 0.3}]}

Effects: mechanics "normal", "shear", "torsion", "slip" and the renderer's effects
(`fv_algos.sim.render.EFFECTS`: "lens", "lighting", "noise", "occlusion", "missing"),
which are passed through to it. Optional top-level keys: "start_mm" [x, y] (object centre, mm), "start_angle_deg",
"initial" {"normal_N", "force_N", "torque_Nmm"} (loads at t = 0), "slide_speed_mm_s" and
"spin_rate_deg_s" (how fast the object moves once a force/torque command exceeds the
friction limit). Without "effects", the effects the steps need are used.

Actions (loads ramp linearly from the previous step's end value to the step's target):
    press    normal_N          ramp the normal load
    shear    force_N [x, y]    ramp the tangential load (past mu P the object slides)
    twist    torque_Nmm        ramp the torque (past the torsional limit it spins), or
             angular_velocity_deg_s   spin the object (gross rotational slip)
    slide    velocity_mm_s [x, y]     drag the object: gross translational slip
    roll     velocity_mm_s [x, y]     roll the object: the patch moves, no traction
    hold     -                 keep everything
    release  -                 ramp normal load, shear and torque to zero
After a slide or a spin the commanded shear / torque is zero (the hysteresis of the
tangential contact is not modelled: loading is treated as monotonic).
"""
from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from fv_algos.sim.objects import SHAPES, Indenter, finite_number, make_object, shape_name
from fv_algos.sim.render import EFFECTS as RENDER_EFFECTS
from fv_algos.text_file import read_utf8
from fv_algos.yaml_loader import YamlLoader

MECHANICS_EFFECTS = frozenset({"normal", "shear", "torsion", "slip"})
EFFECTS = MECHANICS_EFFECTS | RENDER_EFFECTS
DEFAULT_RENDER_EFFECTS = frozenset({"noise", "lighting", "lens"})

_ACTION_KEYS: dict[str, frozenset[str]] = {
    "press": frozenset({"normal_N"}),
    "shear": frozenset({"force_N"}),
    "twist": frozenset({"torque_Nmm", "angular_velocity_deg_s"}),
    "slide": frozenset({"velocity_mm_s"}),
    "roll": frozenset({"velocity_mm_s"}),
    "hold": frozenset(),
    "release": frozenset(),
}

SLIP_KINDS = ("translational", "rotational", "incipient")
NON_SLIP_KINDS = ("pressing", "holding", "shear")
SCENARIO_KINDS = SLIP_KINDS + NON_SLIP_KINDS
# farthest a random slide carries the object, mm: a data-set slide (3 to 8 mm/s for under 1 s) as drawn;
# a longer one (the main job's grasps: 2 s at 30 fps, 4 s at 15 fps) slower, so that the object, which
# starts within 3 mm of the centre, stays on the 24 mm skin (slid off it, the whole load would press on the
# sliver of the object left over the skin)
MAX_SLIDE_MM = 8.0
# farthest the loads of a random slide's shear ramp (1 to 3 frames past the friction limit) carry the object, mm:
# they slip it at the scene's slide_speed_mm_s, 5 mm/s as drawn at 15 fps and more (the data set's and the main job's
# rates), slower below, where the ramp lasts up to 3 / fps s: at 0.5 fps (the camera's random scenarios at fps:=0.5)
# it and the release that follows slid 28 of 40 random slides off the skin
MAX_RAMP_SLIP_MM = 1.0
MAX_SCENE_FRAMES = 100_000  # 55 min at 30 fps: more is no scripted scene (a longer run loops one, or plays random
# scenarios), and a count of frames must be a sane integer (1e308 s made one of infinity); playing its mechanics whole
# (`fv_algos.sim.sensor.check_scene`, 0.7 to 4 ms a frame) takes 1 to 7 min at this count
FRAME_COUNT_TOLERANCE = 1e-9  # relative: a frame count duration * fps this close above a whole number is that number


@dataclass(frozen=True)
class Step:
    """One timed action; unused targets are None. Units as the key names say."""

    action: str
    duration_s: float
    normal_N: float | None = None
    force_N: tuple[float, float] | None = None
    torque_Nmm: float | None = None
    velocity_mm_s: tuple[float, float] | None = None
    angular_velocity_deg_s: float | None = None

    def required_effects(self) -> frozenset[str]:
        """Mechanics effects this step needs."""
        needs = {"normal"}
        if self.action in ("shear", "slide"):
            needs.add("shear")
        if self.action == "slide" or self.angular_velocity_deg_s is not None:
            needs.add("slip")
        if self.action == "twist":
            needs.add("torsion")
        return frozenset(needs)


@dataclass(frozen=True)
class Loads:
    """Normal load N, tangential load (2,) N and torque N*mm."""

    normal_N: float = 0.0
    force_N: tuple[float, float] = (0.0, 0.0)
    torque_Nmm: float = 0.0


@dataclass(frozen=True)
class Scene:
    """A scripted scene. See the module docstring for the description format."""

    obj: Indenter
    fps: float
    effects: frozenset[str]
    steps: tuple[Step, ...]
    start_mm: tuple[float, float] = (0.0, 0.0)
    start_angle_deg: float = 0.0
    initial: Loads = field(default_factory=Loads)
    slide_speed_mm_s: float = 5.0
    spin_rate_deg_s: float = 30.0

    @property
    def duration_s(self) -> float:
        """Total scripted time, s."""
        return float(sum(s.duration_s for s in self.steps))

    @property
    def n_frames(self) -> int:
        """Frames at `fps` covering the script: frame k at t = k / fps for every t < duration_s, i.e.
        ceil(duration_s * fps) (0.5 s at 5 fps: t = 0, 0.2, 0.4). A product within `FRAME_COUNT_TOLERANCE`
        of its size above a whole number is taken as that number: sums of durations carry float error
        (the 1.7 s of launch/scenes/twist_key.yaml at 30 fps is 51.00000000000001 frames: 51)."""
        return max(math.ceil(self.duration_s * self.fps * (1.0 - FRAME_COUNT_TOLERANCE)), 1)


@dataclass(frozen=True)
class Command:
    """What the script asks for at one instant.

    Attributes:
        stamp_s: time, s.
        action: the step's action.
        loads: commanded loads.
        motion: "none", "slide", "spin" or "roll".
        velocity_mm_s: (2,) sliding/rolling velocity, mm/s (zeros otherwise).
        angular_velocity_rad_s: spin rate, rad/s (0 otherwise).
    """

    stamp_s: float
    action: str
    loads: Loads
    motion: str
    velocity_mm_s: tuple[float, float]
    angular_velocity_rad_s: float


def _vector(value: Any, key: str) -> tuple[float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise ValueError(f"{key} must be a list of two numbers [x, y], got {value!r}")
    return (finite_number(value[0], key), finite_number(value[1], key))


def _step_from_dict(desc: Any, index: int) -> Step:
    where = f"steps[{index}]"
    if not isinstance(desc, dict):
        raise ValueError(f"{where} must be a mapping, got {type(desc).__name__}")
    action = desc.get("action")
    if not isinstance(action, str) or action not in _ACTION_KEYS:
        raise ValueError(f"{where}.action must be one of {sorted(_ACTION_KEYS)}, got {action!r}")
    if "duration_s" not in desc:
        raise ValueError(f"{where} needs key 'duration_s'")
    duration = finite_number(desc["duration_s"], f"{where}.duration_s")
    if duration <= 0:
        raise ValueError(f"{where}.duration_s must be > 0, got {duration}")
    allowed = _ACTION_KEYS[action]
    for key in desc:
        if key not in allowed | {"action", "duration_s"}:
            raise ValueError(f"{where}: key {key!r} is not allowed for action {action!r} (allowed: {sorted(allowed)})")
    missing = allowed - set(desc)
    if action == "twist":
        if len(missing) != 1:
            raise ValueError(f"{where}: twist needs exactly one of 'torque_Nmm' or 'angular_velocity_deg_s'")
    elif missing:
        raise ValueError(f"{where}: action {action!r} needs key {sorted(missing)[0]!r}")
    values: dict[str, Any] = {}
    for key in allowed & set(desc):
        name = f"{where}.{key}"
        values[key] = _vector(desc[key], name) if key in ("force_N", "velocity_mm_s") else finite_number(desc[key], name)
    if values.get("normal_N", 0.0) < 0:
        raise ValueError(f"{where}.normal_N must be >= 0, got {values['normal_N']}")
    if values.get("velocity_mm_s") == (0.0, 0.0) or values.get("angular_velocity_deg_s") == 0.0:
        raise ValueError(f"{where}: a {action} at zero speed does not move the object (use hold)")
    return Step(action=action, duration_s=duration, **values)


def _count(frames: float) -> str:
    """A number of frames for a message, in 3 digits (or "over 1e308" for a product past the float range)."""
    return f"{frames:.3g}" if math.isfinite(frames) else "over 1e308"


def _check_frame_count(steps: tuple[Step, ...], fps: float) -> None:
    """ValueError naming the step, or else the steps' sum, when the scene would have more than
    MAX_SCENE_FRAMES frames at `fps` Hz."""
    limit = f"a scene has at most {MAX_SCENE_FRAMES:,} frames ({MAX_SCENE_FRAMES / fps:.4g} s at {fps:g} fps)"
    for i, step in enumerate(steps):
        if step.duration_s * fps > MAX_SCENE_FRAMES:
            raise ValueError(f"steps[{i}].duration_s {step.duration_s:g} s at {fps:g} fps is "
                             f"{_count(step.duration_s * fps)} frames; {limit}")
    total_s = sum(step.duration_s for step in steps)
    if total_s * fps > MAX_SCENE_FRAMES:
        raise ValueError(f"the steps last {total_s:g} s in all, {_count(total_s * fps)} frames at {fps:g} fps; {limit}")


def scene_from_dict(desc: dict[str, Any]) -> Scene:
    """Parse and validate a scene description (see module docstring).

    Raises:
        ValueError: naming the offending key for any bad or missing entry.
    """
    if not isinstance(desc, dict):
        raise ValueError(f"scene description must be a mapping, got {type(desc).__name__}")
    known = {"object", "fps", "effects", "steps", "start_mm", "start_angle_deg", "initial", "slide_speed_mm_s", "spin_rate_deg_s"}
    for key in desc:
        if key not in known:
            raise ValueError(f"scene key {key!r} is unknown (known: {sorted(known)})")
    for key in ("object", "fps", "steps"):
        if key not in desc:
            raise ValueError(f"scene needs key {key!r}")
    obj = make_object(desc["object"])
    fps = finite_number(desc["fps"], "fps")
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if not isinstance(desc["steps"], list) or not desc["steps"]:
        raise ValueError("steps must be a non-empty list")
    steps = tuple(_step_from_dict(s, i) for i, s in enumerate(desc["steps"]))
    _check_frame_count(steps, fps)
    needed = frozenset().union(*(s.required_effects() for s in steps))
    initial_desc = desc.get("initial", {})
    if not isinstance(initial_desc, dict):
        raise ValueError("initial must be a mapping")
    for key in initial_desc:
        if key not in ("normal_N", "force_N", "torque_Nmm"):
            raise ValueError(f"initial key {key!r} is unknown (known: normal_N, force_N, torque_Nmm)")
    initial = Loads(
        normal_N=finite_number(initial_desc.get("normal_N", 0.0), "initial.normal_N"),
        force_N=_vector(initial_desc.get("force_N", [0.0, 0.0]), "initial.force_N"),
        torque_Nmm=finite_number(initial_desc.get("torque_Nmm", 0.0), "initial.torque_Nmm"),
    )
    if initial.normal_N < 0:
        raise ValueError(f"initial.normal_N must be >= 0, got {initial.normal_N}")
    if initial.force_N != (0.0, 0.0):
        needed |= {"shear"}
    if initial.torque_Nmm:
        needed |= {"torsion"}
    if "effects" in desc:
        if not isinstance(desc["effects"], list) or not all(isinstance(name, str) for name in desc["effects"]):
            raise ValueError(f"effects must be a list of names, got {desc['effects']!r}")
        effects = frozenset(desc["effects"])
        repeated = sorted({name for name in desc["effects"] if desc["effects"].count(name) > 1})
        if repeated:
            raise ValueError(f"effects lists {repeated} more than once")
        unknown = effects - EFFECTS
        if unknown:
            raise ValueError(f"effects {sorted(unknown)} unknown (known: {sorted(EFFECTS)})")
        lacking = needed - effects
        if lacking:
            raise ValueError(f"effects lacks {sorted(lacking)}, which the steps need")
    else:
        effects = needed
    start = _vector(desc.get("start_mm", [0.0, 0.0]), "start_mm")
    rates = {k: finite_number(desc.get(k, d), k) for k, d in (("slide_speed_mm_s", 5.0), ("spin_rate_deg_s", 30.0))}
    for key, rate in rates.items():
        if rate <= 0:
            raise ValueError(f"{key} must be > 0, got {rate}")
    return Scene(obj, fps, effects, steps, start, finite_number(desc.get("start_angle_deg", 0.0), "start_angle_deg"), initial, **rates)


def load_scene(path: str | Path) -> Scene:
    """Read a scene description from a .yaml/.yml or .json file (UTF-8).

    Raises:
        ValueError: "<path>: what is wrong" (or "<path> line <n>: ..." for text that is not UTF-8),
            the line too for text that is not YAML / JSON; OSError "<path>: cannot be read (<reason>)".
            Every message starts with the path, so callers add what they are without naming it again.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".yaml", ".yml", ".json"):
        raise ValueError(f"{path}: a scene file must end in .yaml, .yml or .json")
    try:
        text = read_utf8(path)
    except OSError as exc:
        raise OSError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    try:
        desc = json.loads(text) if suffix == ".json" else yaml.load(text, Loader=YamlLoader)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        raise ValueError(f"{path}: not YAML: {where}{getattr(exc, 'problem', None) or exc}") from None
    try:
        return scene_from_dict(desc)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _end_loads(step: Step, start: Loads) -> Loads:
    """Loads at the end of a step that began at `start`."""
    if step.action == "press":
        return Loads(float(step.normal_N), start.force_N, start.torque_Nmm)
    if step.action == "shear":
        return Loads(start.normal_N, step.force_N, start.torque_Nmm)
    if step.action == "twist":
        torque = step.torque_Nmm if step.torque_Nmm is not None else 0.0
        return Loads(start.normal_N, start.force_N if step.torque_Nmm is not None else (0.0, 0.0), float(torque))
    if step.action == "slide":
        return Loads(start.normal_N, (0.0, 0.0), start.torque_Nmm)
    if step.action == "release":
        return Loads()
    return start


def _lerp(a: Loads, b: Loads, s: float) -> Loads:
    return Loads(
        a.normal_N + s * (b.normal_N - a.normal_N),
        (a.force_N[0] + s * (b.force_N[0] - a.force_N[0]), a.force_N[1] + s * (b.force_N[1] - a.force_N[1])),
        a.torque_Nmm + s * (b.torque_Nmm - a.torque_Nmm),
    )


def _step_bounds(scene: Scene) -> np.ndarray:
    """(len(steps) + 1,) start time of every step and the scene's end, s."""
    return np.cumsum([0.0] + [s.duration_s for s in scene.steps])


def scene_commands(scene: Scene) -> Iterator[Command]:
    """The commanded loads and motions at every frame time t_k = k / fps, k < n_frames, one at a time."""
    starts = [scene.initial]
    for step in scene.steps:
        starts.append(_end_loads(step, starts[-1]))
    bounds = _step_bounds(scene)
    for k in range(scene.n_frames):
        t = k / scene.fps
        i = min(int(np.searchsorted(bounds, t, side="right")) - 1, len(scene.steps) - 1)
        step = scene.steps[i]
        s = min((t - bounds[i]) / step.duration_s, 1.0)
        loads = _lerp(starts[i], starts[i + 1], s)
        motion, velocity, spin = "none", (0.0, 0.0), 0.0
        if step.action in ("slide", "roll"):
            motion, velocity = step.action, step.velocity_mm_s
        elif step.action == "twist" and step.angular_velocity_deg_s is not None:
            motion, spin = "spin", float(np.radians(step.angular_velocity_deg_s))
        yield Command(t, step.action, loads, motion, velocity, spin)


def scripted_motion(scene: Scene, t0_s: float, t1_s: float) -> tuple[np.ndarray, float]:
    """How far the steps move the object between ``t0_s`` and ``t1_s`` (slides and rolls: (2,) mm;
    spins: rad), integrated over the time each step overlaps the interval, so a slide goes its velocity
    times its duration whatever the frame rate."""
    bounds = _step_bounds(scene)
    shift, turn = np.zeros(2), 0.0
    for step, start, end in zip(scene.steps, bounds[:-1], bounds[1:]):
        overlap = min(end, t1_s) - max(start, t0_s)
        if overlap <= 0:
            continue
        if step.action in ("slide", "roll"):
            shift += np.asarray(step.velocity_mm_s) * overlap
        elif step.action == "twist" and step.angular_velocity_deg_s is not None:
            turn += float(np.radians(step.angular_velocity_deg_s)) * overlap
    return shift, turn


def _unit(rng: np.random.Generator) -> np.ndarray:
    angle = rng.uniform(0.0, 2.0 * np.pi)
    return np.array([np.cos(angle), np.sin(angle)])


def random_scenario(
    rng: np.random.Generator,
    kind: str,
    n_frames: int = 15,
    fps: float = 15.0,
    render_effects: frozenset[str] = DEFAULT_RENDER_EFFECTS,
) -> Scene:
    """A random scene of one slip / no-slip kind (the paper's data protocol).

    Kinds and what they guarantee over all n_frames (so any 10-frame window of a slip
    sequence contains slip):
        translational  gross sliding from frame <= 3 on (shear past mu P, which slides the object
                       at most MAX_RAMP_SLIP_MM, then a slide of at 3 to 8 mm/s and at most
                       MAX_SLIDE_MM);
        rotational     gross spinning from frame <= 2 on (non-axisymmetric objects, so
                       the spin moves the patch);
        incipient      shear ramped from 0.8 to 0.97 mu P on curved objects (slip-zone
                       share >= 0.5 throughout);
        pressing       normal load ramp, a third of them each: loading from a light touch
                       (0.2-1 N, no shear), from rest (the contact appears over 4 frames
                       or more, then is held) or a release (the load and a light shear,
                       <= 0.3 mu P, back to zero over 4 frames or more, after a hold):
                       what a gripper does before and after the motion;
        holding        constant load with shear <= 0.3 mu P;
        shear          hard negatives: shear ramped to 0.3-0.45 mu P, still stuck.
    Args:
        rng: random generator (all randomness comes from it).
        kind: one of SCENARIO_KINDS.
        n_frames: frames in the sequence (>= 4).
        fps: frame rate, Hz.
        render_effects: render effects to list in the scene.
    """
    if kind not in SCENARIO_KINDS:
        raise ValueError(f"kind must be one of {SCENARIO_KINDS}, got {kind!r}")
    if n_frames < 4 or fps <= 0:
        raise ValueError(f"need n_frames >= 4 and fps > 0, got {n_frames}, {fps}")
    if kind == "rotational":
        pool = [c for c in SHAPES.values() if not c.AXISYMMETRIC]
    elif kind == "incipient":
        pool = [c for c in SHAPES.values() if not c.FLAT]
    else:
        pool = list(SHAPES.values())
    obj = pool[int(rng.integers(len(pool)))].random(rng)
    duration = n_frames / fps
    normal = float(rng.uniform(1.0, 4.0))
    limit = obj.mu * normal
    direction = _unit(rng)
    start = tuple(float(v) for v in rng.uniform(-3.0, 3.0, size=2))
    angle = float(rng.uniform(0.0, 360.0))

    def vec(ratio: float) -> list[float]:
        return [float(v) for v in direction * ratio * limit]

    initial: dict[str, Any] = {"normal_N": normal}
    rates: dict[str, float] = {}
    if kind == "translational":
        initial["force_N"] = vec(float(rng.uniform(0.2, 0.5)))
        ramp = float(rng.integers(1, 4)) / fps
        speed = min(float(rng.uniform(3.0, 8.0)), MAX_SLIDE_MM / (duration - ramp))
        rates["slide_speed_mm_s"] = min(Scene.slide_speed_mm_s, MAX_RAMP_SLIP_MM / ramp)
        steps = [
            {"action": "shear", "duration_s": ramp, "force_N": vec(1.2)},
            {"action": "slide", "duration_s": duration - ramp, "velocity_mm_s": [float(v) for v in direction * speed]},
        ]
        effects = {"normal", "shear", "slip"}
    elif kind == "rotational":
        hold = float(rng.integers(0, 3)) / fps
        rate = float(rng.uniform(20.0, 60.0)) * float(rng.choice([-1.0, 1.0]))
        steps = [{"action": "twist", "duration_s": duration - hold, "angular_velocity_deg_s": rate}]
        if hold > 0:
            steps.insert(0, {"action": "hold", "duration_s": hold})
        effects = {"normal", "torsion", "slip"}
    elif kind == "incipient":
        initial["force_N"] = vec(0.8)
        steps = [{"action": "shear", "duration_s": duration, "force_N": vec(float(rng.uniform(0.93, 0.97)))}]
        effects = {"normal", "shear"}
    elif kind == "pressing":
        mode = int(rng.integers(3))
        ramp = float(rng.integers(4, n_frames + 1)) / fps  # drawn for every mode: the data set's draws stay as shipped
        held = [{"action": "hold", "duration_s": duration - ramp}] if duration - ramp > 1e-9 else []
        if mode == 0:  # loading from a light touch
            initial["normal_N"] = float(rng.uniform(0.2, 1.0))
            steps = [{"action": "press", "duration_s": duration, "normal_N": normal + 1.0}]
            effects = {"normal"}
        elif mode == 1:  # from rest: the contact appears, then is held
            initial["normal_N"] = 0.0
            steps = [{"action": "press", "duration_s": ramp, "normal_N": normal}, *held]
            effects = {"normal"}
        else:  # a release, after a hold: the normal load and a light shear back to zero
            initial["force_N"] = vec(float(rng.uniform(0.0, 0.3)))
            steps = [*held, {"action": "release", "duration_s": ramp}]
            effects = {"normal", "shear"}
    elif kind == "holding":
        initial["force_N"] = vec(float(rng.uniform(0.0, 0.3)))
        steps = [{"action": "hold", "duration_s": duration}]
        effects = {"normal", "shear"}
    else:
        steps = [{"action": "shear", "duration_s": duration, "force_N": vec(float(rng.uniform(0.3, 0.45)))}]
        effects = {"normal", "shear"}
    desc = {"object": {"shape": shape_name(obj), **{k: getattr(obj, k) for k in obj.RANGES}}, "fps": fps, "effects": sorted(effects | set(render_effects)), "steps": steps, "start_mm": list(start), "start_angle_deg": angle, "initial": initial, **rates}
    return scene_from_dict(desc)


def grasp_scene(scene: Scene, approach_s: float = 0.5, release_s: float = 0.4, rest_s: float = 0.2) -> Scene:
    """``scene`` as one whole grasp of a skin at rest, as a gripper makes it: the loads it starts with
    (``scene.initial``) are reached from zero by a press over ``approach_s`` s (then a shear and a twist,
    ``approach_s`` / 2 s each, for the tangential load and torque it starts with), its steps follow, a
    release takes every load back to zero over ``release_s`` s, and the skin rests for ``rest_s`` s.

    A random scenario (:func:`random_scenario`, the paper's data protocol) starts loaded, its fields
    measured from the rest skin. Played one after another, such scenarios jump from one loaded contact
    to the next and the skin is never at rest, so a tracker's reference (the first frame) is a loaded
    skin and every field after it is off; grasps begin and end at rest.
    """
    if min(approach_s, release_s, rest_s) <= 0:
        raise ValueError(f"approach_s, release_s and rest_s must be > 0, got {approach_s}, {release_s}, {rest_s}")
    start = scene.initial
    steps = [Step("press", approach_s, normal_N=start.normal_N)]
    if any(start.force_N):
        steps.append(Step("shear", approach_s / 2, force_N=start.force_N))
    if start.torque_Nmm:
        steps.append(Step("twist", approach_s / 2, torque_Nmm=start.torque_Nmm))
    steps += [*scene.steps, Step("release", release_s), Step("hold", rest_s)]
    return replace(scene, steps=tuple(steps), initial=Loads())


def noisy_labels(labels: np.ndarray, rng: np.random.Generator, flip_probability: float = 0.0, max_onset_shift_frames: int = 0) -> np.ndarray:
    """Per-frame slip labels with human-like labelling noise.

    Args:
        labels: (T,) bool true per-frame slip labels.
        rng: random generator.
        flip_probability: chance that the whole sequence's labels are inverted.
        max_onset_shift_frames: the slip onset (first True) is moved by a uniform integer
            shift in [-max, +max] frames (clamped to the sequence).
    Returns:
        (T,) bool noisy labels.
    """
    out = np.asarray(labels, dtype=bool).copy()
    if out.ndim != 1:
        raise ValueError(f"labels must be 1-D, got shape {out.shape}")
    if not (0.0 <= flip_probability <= 1.0) or max_onset_shift_frames < 0:
        raise ValueError(f"flip_probability must be in [0, 1] and max_onset_shift_frames >= 0, got {flip_probability}, {max_onset_shift_frames}")
    if out.any() and max_onset_shift_frames > 0:
        onset = int(np.argmax(out))
        shifted = int(np.clip(onset + rng.integers(-max_onset_shift_frames, max_onset_shift_frames + 1), 0, len(out) - 1))
        out[min(onset, shifted):max(onset, shifted)] = shifted < onset
    if rng.random() < flip_probability:
        out = ~out
    return out
