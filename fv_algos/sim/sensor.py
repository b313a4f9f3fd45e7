"""The simulated sensor: scene -> contact mechanics -> renderer -> frame + ground truth.

`SceneRunner` steps a scene's mechanics (object pose, loads, contact state) frame by
frame; `check_scene` plays them without rendering, to refuse a scene that cannot be played before
any frame is shown; `SimSensor` adds the fisheye renderer and per-frame ground truth (`SimSensor.frames`:
from a frame on, the frames before it played but not rendered); `write_sequence`
stores frames (PNG) and truth (npz + json) for inspection; `preview_image` draws the true
markers and displacement arrows over a frame.
"""
from __future__ import annotations

import itertools
import json
import secrets
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from fv_algos.atomic_file import write_image
from fv_algos.fisheye import DEFAULT_CAMERA_DISTANCE_MM, FisheyeCamera
from fv_algos.sim.contact import ContactModel, ContactParams, ContactState
from fv_algos.sim.halfspace import SurfaceGrid
from fv_algos.sim.render import RenderParams, SkinRenderer
from fv_algos.sim.render import EFFECTS as RENDER_EFFECTS
from fv_algos.sim.scene import (DEFAULT_RENDER_EFFECTS, SCENARIO_KINDS, Command, Scene, grasp_scene, random_scenario,
                                scene_commands, scripted_motion)
from fv_algos.sim.skin import SkinParams, marker_grid_mm


@dataclass(frozen=True)
class SensorParams:
    """Everything that defines the simulated sensor, defaults in one place.

    Attributes:
        skin: skin geometry and material.
        contact: contact solver settings (incl. the incipient-slip threshold).
        render: renderer appearance.
        camera_distance_mm: camera centre to undeformed skin, mm.
    """

    skin: SkinParams = field(default_factory=SkinParams)
    contact: ContactParams = field(default_factory=ContactParams)
    render: RenderParams = field(default_factory=RenderParams)
    camera_distance_mm: float = DEFAULT_CAMERA_DISTANCE_MM


@dataclass
class MechanicsFrame:
    """Mechanics of one frame: the command, the object pose and the contact state.

    Attributes:
        index: frame index within the scene.
        command: what the script asked for.
        centre_mm: (2,) object centre on the skin, mm.
        angle_rad: object rotation about the skin normal, rad.
        state: the contact solution.
    """

    index: int
    command: Command
    centre_mm: np.ndarray
    angle_rad: float
    state: ContactState


def _mm(value: float) -> str:
    """A position in mm for a message: 2 decimals, or 3 digits and an exponent past 1e4 (a slide at 1e300
    mm/s put the object 300 digits away)."""
    return f"{value:.2f}" if abs(value) < 1e4 else f"{value:.3g}"


class SceneRunner:
    """Steps a scene's mechanics; gross slip moves the object only with the "slip" effect."""

    def __init__(self, scene: Scene, skin: SkinParams, contact: ContactParams) -> None:
        self.scene = scene
        self.model = ContactModel(skin, contact)
        self._effects = frozenset(scene.effects)
        self._half_size_mm = skin.size_mm / 2.0

    def __len__(self) -> int:
        return self.scene.n_frames

    def __iter__(self) -> Iterator[MechanicsFrame]:
        """Yields MechanicsFrame for frames 0 .. n_frames - 1. Between two frames the object moves as
        the steps script it (:func:`fv_algos.sim.scene.scripted_motion`), or, where the loads alone pass
        the friction limit (gross slip with the "slip" effect), at the scene's slide speed / spin rate."""
        scene = self.scene
        self.model.reset()
        centre = np.array(scene.start_mm, dtype=np.float64)
        angle = float(np.radians(scene.start_angle_deg))
        dt = 1.0 / scene.fps
        for k, cmd in enumerate(scene_commands(scene)):
            velocity = np.array(cmd.velocity_mm_s, dtype=np.float64)
            speed = float(np.hypot(*velocity))
            direction = velocity / speed if speed > 0 else np.zeros(2)
            if cmd.motion == "spin":
                direction = np.array([np.sign(cmd.angular_velocity_rad_s), 0.0])
            if np.abs(centre).max() > self._half_size_mm + 1e-9:  # its load would all press on the skin's rim
                raise ValueError(f"frame {k} (t = {cmd.stamp_s:.3f} s): the object's centre ({_mm(centre[0])}, "
                                 f"{_mm(centre[1])}) mm has left the skin, which spans +-{self._half_size_mm:g} mm")
            state = self.model.solve(
                scene.obj, centre, angle, cmd.loads.normal_N, np.array(cmd.loads.force_N), cmd.loads.torque_Nmm,
                cmd.motion if cmd.motion == "roll" or "slip" in self._effects else "none", direction, self._effects,
            )
            if state.slip_state == "gross" and cmd.motion == "none" and "slip" not in self._effects:
                raise ValueError(f"frame {k} (t = {cmd.stamp_s:.3f} s): the loads pass the friction limit (gross "
                                 f"{state.slip_type} slip) but the scene lacks the 'slip' effect that moves the object")
            yield MechanicsFrame(k, cmd, centre.copy(), angle, state)
            shift, turn = scripted_motion(scene, cmd.stamp_s, (k + 1) * dt)
            centre, angle = centre + shift, angle + turn
            if cmd.motion == "none" and state.slip_state == "gross" and "slip" in self._effects:
                if state.slip_type == "translational":
                    force = np.array(cmd.loads.force_N)
                    centre = centre + scene.slide_speed_mm_s * dt * force / max(float(np.hypot(*force)), 1e-12)
                else:
                    angle += float(np.sign(cmd.loads.torque_Nmm)) * np.radians(scene.spin_rate_deg_s) * dt


@dataclass
class FrameTruth:
    """Ground truth of one simulated frame.

    Attributes:
        index: frame index since the sensor started.
        markers_ref_mm: (N, 2) float64 marker rest positions on the skin, mm.
        marker_displacement_mm: (N, 3) float64 marker displacement (ux, uy, uz), mm; uz
            toward the camera.
        markers_px: (N, 2) float64 true image centres of the displaced markers, px.
        visible: (N,) bool markers fully visible in the image.
        mechanics: the frame's mechanics (pose, loads, contact state with pressure,
            traction, displacement field, contact and slip masks on `grid`).
        grid: the mechanics grid the fields live on.
        camera: the camera model.
        camera_distance_mm: camera centre to undeformed skin, mm.
        lens: whether the fisheye distortion was rendered.
    """

    index: int
    markers_ref_mm: np.ndarray
    marker_displacement_mm: np.ndarray
    markers_px: np.ndarray
    visible: np.ndarray
    mechanics: MechanicsFrame
    grid: SurfaceGrid
    camera: FisheyeCamera
    camera_distance_mm: float
    lens: bool

    @property
    def slip_state(self) -> str:
        """"stick", "incipient" or "gross" (see ContactState)."""
        return self.mechanics.state.slip_state

    @property
    def slip_type(self) -> str:
        """"none", "translational" or "rotational"."""
        return self.mechanics.state.slip_type

    @property
    def is_slip(self) -> bool:
        """Incipient or gross slip: the paper's slip label."""
        return self.mechanics.state.is_slip

    @property
    def contact_area_mm2(self) -> float:
        """Contact patch area, mm^2 (0 without contact)."""
        return float(self.mechanics.state.contact.sum() * self.grid.cell_area_mm2)

    @property
    def contact_centre_mm(self) -> np.ndarray:
        """(2,) pressure-weighted contact centre, mm; the object centre when there is no contact."""
        p = self.mechanics.state.pressure_mpa
        total = p.sum()
        if total <= 0:
            return self.mechanics.centre_mm.copy()
        x, y = self.grid.mesh_mm()
        return np.array([np.sum(p * x) / total, np.sum(p * y) / total])

    @property
    def markers_ref_px(self) -> np.ndarray:
        """(N, 2) float64 image centres of the markers at rest, px."""
        ref = np.column_stack([self.markers_ref_mm, np.full(len(self.markers_ref_mm), self.camera_distance_mm)])
        return self.camera.project(ref, lens=self.lens)

    def image_displacement_px(self, points_px: np.ndarray) -> np.ndarray:
        """True image-plane displacement at reference (undeformed) image points.

        Each point is unprojected to the undeformed skin plane, displaced by the skin
        displacement there and projected again.

        Args:
            points_px: (M, 2) float64 reference image points, px.
        Returns:
            (M, 2) float64 displacement, px; zero for points whose skin point is off the skin.
        """
        pts = np.asarray(points_px, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or not np.all(np.isfinite(pts)):
            raise ValueError(f"points_px must be a finite (M, 2) array, got shape {pts.shape}")
        d = self.camera_distance_mm
        skin_xy = self.camera.unproject_to_plane(pts, d, lens=self.lens)
        u = self.grid.sample(self.mechanics.state.displacement_mm, skin_xy)
        ref = np.column_stack([skin_xy, np.full(len(pts), d)])
        moved = np.column_stack([skin_xy[:, 0] + u[0], skin_xy[:, 1] + u[1], d - u[2]])
        return self.camera.project(moved, lens=self.lens) - self.camera.project(ref, lens=self.lens)


@dataclass
class SimFrame:
    """One simulated camera frame: (H, W) uint8 image, time stamp s, ground truth."""

    image: np.ndarray
    stamp_s: float
    truth: FrameTruth


class SimSensor:
    """Simulated FingerVision camera, deterministic from its seed.

    With a scene it plays that scene once; with `scene=None` it loops over random
    scenarios of all kinds (`random_loop_frames` frames each) forever, each played as a whole
    grasp from the skin at rest (:func:`fv_algos.sim.scene.grasp_scene`: pressed to its first loads
    over 0.5 s, released over 0.4 s after it, then 0.2 s at rest).
    """

    def __init__(
        self,
        scene: Scene | None,
        params: SensorParams | None = None,
        camera: FisheyeCamera | None = None,
        seed: int = 0,
        loop_fps: float = 60.0,
        random_loop_frames: int = 60,
        render_effects: frozenset[str] = DEFAULT_RENDER_EFFECTS,
    ) -> None:
        """
        Args:
            scene: the scene to play, or None for the looping random-scenario mode.
            params: sensor parameters (defaults: SensorParams()).
            camera: camera model (default FisheyeCamera.default()).
            seed: seed of the renderer and of the random scenarios.
            loop_fps: frame rate of the random scenarios, Hz (random mode only).
            random_loop_frames: frames of each random scenario, not counting the grasp's press and
                release around it (random mode only).
            render_effects: render effects of the random mode (a scene brings its own).
        """
        self.params = params if params is not None else SensorParams()
        self.camera = camera if camera is not None else FisheyeCamera.default()
        self.scene = scene
        self._rng = np.random.default_rng(seed)
        self._loop_fps = float(loop_fps)
        self._loop_frames = int(random_loop_frames)
        effects = (scene.effects if scene is not None else frozenset(render_effects)) & RENDER_EFFECTS
        skin = self.params.skin
        self.renderer = SkinRenderer(self.camera, self.params.camera_distance_mm, skin.marker_diameter_mm, self.params.render, effects, seed)
        self.markers_ref_mm = marker_grid_mm(skin)
        self._lens = "lens" in effects
        self._index = 0
        self._time_offset_s = 0.0
        self.last_frame_s = 0.0

    def _scenes(self) -> Iterator[Scene]:
        if self.scene is not None:
            yield self.scene
            return
        while True:
            kind = SCENARIO_KINDS[int(self._rng.integers(len(SCENARIO_KINDS)))]
            scenario = random_scenario(self._rng, kind, self._loop_frames, self._loop_fps, self.renderer.effects)
            yield grasp_scene(scenario)

    def __iter__(self) -> Iterator[SimFrame]:
        """Yields SimFrame; finite for a scene, endless in random mode (`frames` from the sensor's next frame)."""
        return self.frames()

    def frames(self, start: int = 0) -> Iterator[SimFrame]:
        """Yields the SimFrames that iterating yields from frame index `start` on: the frames before it
        are played (their mechanics, which later frames may depend on, e.g. a slide's gross slip) and
        skipped by the renderer, never rendered. Frame N of a scene costs its mechanics up to N and one
        rendered frame.

        Args:
            start: index of the first frame yielded, counted from the sensor's first frame (a sensor
                iterated before has used up its first ones). Past a scene's end nothing is yielded.
        Raises:
            ValueError: naming the frame, when a frame cannot be played (`_marker_mechanics`;
                `check_scene` finds it without rendering), a skipped one too.
        """
        skin = self.params.skin
        for scene in self._scenes():
            runner = SceneRunner(scene, skin, self.params.contact)
            started = time.perf_counter()
            for mech, u in _marker_mechanics(runner, skin, self.params.camera_distance_mm):
                if self._index < start:
                    self.renderer.skip(len(self.markers_ref_mm))
                    self._index += 1
                    continue
                result = self.renderer.render(np.column_stack([self.markers_ref_mm + u[:, :2], u[:, 2]]))
                truth = FrameTruth(self._index, self.markers_ref_mm, u, result.markers_px, result.visible, mech, runner.model.grid, self.camera, self.params.camera_distance_mm, self._lens)
                self.last_frame_s = time.perf_counter() - started
                yield SimFrame(result.image, self._time_offset_s + mech.command.stamp_s, truth)
                self._index += 1
                started = time.perf_counter()
            self._time_offset_s += scene.n_frames / scene.fps


def _marker_mechanics(runner: SceneRunner, skin: SkinParams,
                      camera_distance_mm: float) -> Iterator[tuple[MechanicsFrame, np.ndarray]]:
    """The frames of `runner` with the (N, 3) displacement (ux, uy, uz), mm, of the markers of `skin` at rest
    (`marker_grid_mm`, row-major).

    Raises:
        ValueError: naming the frame, as `SceneRunner` does, when a frame cannot be played: besides
            SceneRunner's, loads that push markers to the camera, `camera_distance_mm` from the skin (the
            half-space skin has no thickness that would stop them), naming what pushes them, and loads that
            fold the skin (`_folded_cells`), naming them.
    """
    markers_ref_mm = marker_grid_mm(skin)
    for mech in runner:
        u = runner.model.grid.sample(mech.state.displacement_mm, markers_ref_mm).T
        reaching = np.flatnonzero(u[:, 2] >= camera_distance_mm)
        when = f"frame {mech.index} (t = {mech.command.stamp_s:.3f} s): "
        if reaching.size:
            raise ValueError(when + _pushed_to_camera(mech, runner.model, markers_ref_mm, reaching, camera_distance_mm))
        folded = _folded_cells(markers_ref_mm + u[:, :2], (skin.n_markers_y, skin.n_markers_x))
        if folded:
            cells = (skin.n_markers_y - 1) * (skin.n_markers_x - 1)
            raise ValueError(when + f"{_loads(mech)} fold the skin: {folded} of the {cells} cells between "
                             "neighbouring markers turn over (markers pass each other), which no skin does; lower the "
                             "shear or the load (or raise the skin's modulus)")
        yield mech, u


def _folded_cells(markers_mm: np.ndarray, shape: tuple[int, int]) -> int:
    """How many cells of the marker grid, whose markers (row-major, `shape` = (rows, columns)) lie at
    `markers_mm` (N, 2) mm in the skin plane, are turned over: either of the cell's two triangles of
    neighbouring markers has lost its positive area. The linear half-space moves markers through one another
    under a shear it cannot carry (a 68 N shear of a sphere pressed with 60 N at friction 1.2), and wrote that
    as the frame's truth."""
    p = markers_mm.reshape(*shape, 2)
    a, b, c, d = p[:-1, :-1], p[:-1, 1:], p[1:, :-1], p[1:, 1:]  # (row, col), (row, col + 1), (row + 1, col), ...

    def area(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:  # twice the signed area
        (x1, y1), (x2, y2) = np.moveaxis(p1 - p0, -1, 0), np.moveaxis(p2 - p0, -1, 0)
        return x1 * y2 - y1 * x2

    return int(np.count_nonzero((area(a, b, c) <= 0) | (area(d, c, b) <= 0)))


def _load_words(state: ContactState) -> dict[str, str]:
    """The frame's loads as the contact carries them, in words: {"load": "the normal load of 60 N", "shear": "the
    shear of 68 N", "torque": "the torque of 0 N*mm"}."""
    return {"load": f"the normal load of {state.normal_N:g} N",
            "shear": f"the shear of {float(np.hypot(*state.force_N)):g} N",
            "torque": f"the torque of {abs(state.torque_Nmm):g} N*mm"}


def _loads(mech: MechanicsFrame) -> str:
    """The frame's non-zero loads in words: "the normal load of 60 N and the shear of 68 N"."""
    state, words = mech.state, _load_words(mech.state)
    carried = {"load": True, "shear": bool(np.any(state.force_N)), "torque": bool(state.torque_Nmm)}
    return " and ".join(words[name] for name, present in carried.items() if present)


def check_scene(scene: Scene, params: SensorParams | None = None, frames: int | None = None) -> None:
    """Play the mechanics of the first `frames` frames of `scene` (None: all) on the sensor of `params`
    (default SensorParams()) without rendering a frame: the ValueError that `SimSensor` would raise at the
    first frame it cannot play (an object that leaves the skin, markers pushed to the camera, ...), before
    any frame is shown. It costs 0.7 to 5.5 ms a frame (a sphere's closed form to a twisting key's
    numerical contact), a tenth to a half of a rendered frame: 0.06 s for launch/scenes/press_shear_slide.yaml,
    0.19 s for twist_key.yaml."""
    params = params if params is not None else SensorParams()
    runner = SceneRunner(scene, params.skin, params.contact)
    for _ in itertools.islice(_marker_mechanics(runner, params.skin, params.camera_distance_mm), frames):
        pass


def _pushed_to_camera(mech: MechanicsFrame, model: ContactModel, markers_ref_mm: np.ndarray, rows: np.ndarray,
                      camera_distance_mm: float) -> str:
    """What pushes the markers `rows` (indices into `markers_ref_mm`) to the camera in the frame `mech`:
    its normal load, or the shear and torque it asks for (a force, a slide; a torque, a spin), whose
    tractions move the skin toward the camera too (the half-space's coupling term, (1 - 2 nu)), where
    the pressure alone would push fewer of them. Loads as the contact carries them."""
    state, command = mech.state, mech.command
    reach = f"{len(rows)} of the {len(markers_ref_mm)} markers to the camera, {camera_distance_mm:g} mm from the skin"
    words = _load_words(state)
    load = words["load"]
    uz = model.grid.sample(model.halfspace.normal_displacement_mm(state.pressure_mpa), markers_ref_mm[rows])
    by_load = int(np.count_nonzero(uz >= camera_distance_mm))
    asked = {"shear": any(command.loads.force_N) or command.motion == "slide",
             "torque": bool(command.loads.torque_Nmm) or command.motion == "spin"}
    causes = {cause: words[cause] for cause, given in asked.items() if given}
    if by_load == len(rows) or not causes:
        return f"{load} pushes {reach}; lower the load"
    verb = "pushes" if len(causes) == 1 else "push"
    return (f"{' and '.join(causes.values())} {verb} {reach}, through the coupling of shear and normal displacement "
            f"({load} alone pushes {by_load or 'none'}); lower the {' and the '.join(causes)}"
            + (" and the load" if by_load else ""))


def preview_image(frame: SimFrame, arrow_scale: float = 5.0) -> np.ndarray:
    """The frame in colour with true marker centres (green) and displacement arrows (red).

    Args:
        frame: a simulated frame.
        arrow_scale: arrow length per px of image displacement.
    Returns:
        (H, W, 3) uint8 BGR image.
    """
    out = cv2.cvtColor(frame.image, cv2.COLOR_GRAY2BGR)
    truth = frame.truth
    rest = truth.markers_ref_px
    for (u0, v0), (u1, v1), ok in zip(rest, truth.markers_px, truth.visible):
        if not ok:
            continue
        cv2.circle(out, (int(round(u1)), int(round(v1))), 2, (0, 200, 0), -1, cv2.LINE_AA)
        tip = (int(round(u0 + arrow_scale * (u1 - u0))), int(round(v0 + arrow_scale * (v1 - v0))))
        cv2.arrowedLine(out, (int(round(u0)), int(round(v0))), tip, (0, 0, 255), 1, cv2.LINE_AA, tipLength=0.3)
    state = truth.mechanics.state
    label = f"{state.slip_state} {state.slip_type}  P={state.normal_N:.2f}N"
    cv2.putText(out, label, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 255, 255), 1, cv2.LINE_AA)
    return out


def write_sequence(sensor: SimSensor, out_dir: str | Path, n_frames: int) -> int:
    """Write the first `n_frames` frames (fewer when the scene ends first) as PNG plus ground truth for
    inspection, into a new or empty folder `out_dir`. The files are written to a new folder of its own
    beside it (`out_dir` + ".partial-" + a random suffix) and that folder renamed once all are there, so a
    failure (e.g. a scene that slides its object off the skin) leaves no folder of some frames without
    their truth; it removes its own partial folder, and never a folder it did not make.

    Files: frame_%05d.png, preview_%05d.png, truth.npz (stamp_s (T,), markers_ref_mm
    (N, 2), marker_displacement_mm (T, N, 3), markers_px (T, N, 2), visible (T, N),
    contact (T, n, n), slip (T, n, n), displacement_mm (T, 3, n, n), slip_label (T,)),
    truth.json (per-frame slip state/type, loads, contact area and centre, pose).

    Returns:
        T, the frames written.
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    out = Path(out_dir).resolve()  # "." has no name to put ".partial-" after
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out} is not a new or empty folder")
    partial = out.with_name(f"{out.name}.partial-{secrets.token_hex(4)}")
    partial.mkdir(parents=True)  # a new name: a folder that exists (someone else's) is never taken or removed
    try:
        try:
            written = _write_frames(sensor, partial, n_frames)
        except OSError as exc:  # numpy's and json's errors do not name the file (a full disk: "[Errno 28] ...")
            raise OSError(exc.errno, exc.strerror, str(out)) if exc.filename is None and exc.errno else exc
        if out.exists():
            out.rmdir()
        partial.rename(out)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return written


def _write_frames(sensor: SimSensor, out: Path, n_frames: int) -> int:
    """The files of :func:`write_sequence`, into the folder `out`; returns the frames written."""
    arrays: dict[str, list[np.ndarray]] = {k: [] for k in ("stamp_s", "marker_displacement_mm", "markers_px", "visible", "contact", "slip", "displacement_mm", "slip_label")}
    records = []
    for i, frame in zip(range(n_frames), sensor):
        t = frame.truth
        state = t.mechanics.state
        write_image(out / f"frame_{i:05d}.png", frame.image)
        write_image(out / f"preview_{i:05d}.png", preview_image(frame))
        for key, value in (("stamp_s", frame.stamp_s), ("marker_displacement_mm", t.marker_displacement_mm), ("markers_px", t.markers_px), ("visible", t.visible), ("contact", state.contact), ("slip", state.slip), ("displacement_mm", state.displacement_mm), ("slip_label", t.is_slip)):
            arrays[key].append(np.asarray(value))
        records.append({
            "index": i, "stamp_s": frame.stamp_s, "action": t.mechanics.command.action,
            "slip_state": state.slip_state, "slip_type": state.slip_type, "slip_share": state.slip_share,
            "normal_N": state.normal_N, "force_N": state.force_N.tolist(), "torque_Nmm": state.torque_Nmm,
            "contact_area_mm2": t.contact_area_mm2, "contact_centre_mm": t.contact_centre_mm.tolist(),
            "object_centre_mm": t.mechanics.centre_mm.tolist(), "object_angle_rad": t.mechanics.angle_rad,
            "converged": state.converged,
        })
    np.savez_compressed(out / "truth.npz", markers_ref_mm=sensor.markers_ref_mm, **{k: np.stack(v) for k, v in arrays.items()})
    (out / "truth.json").write_text(json.dumps({"frames": records}, indent=1))
    return len(records)
