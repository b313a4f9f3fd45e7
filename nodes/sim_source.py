"""The simulated sensor as a camera-node frame source."""
from __future__ import annotations

import dataclasses
import hashlib
import time
from typing import Iterator

import numpy as np

from fv_algos.fisheye import FisheyeCamera
from fv_algos.sim.scene import Scene, load_scene
from fv_algos.sim.sensor import SimSensor, check_scene
from nodes import launch_checks
from nodes.camera_sources import Frame, SourceConfigError, SourceError, log


def source_name(scene_path: str) -> str:
    """How the simulated source of the scene file ``scene_path`` ("": random scenarios) is named."""
    return f"sim {scene_path or 'random scenarios'}"


def _image_size() -> tuple[int, int]:
    """(width, height) px of the simulator's camera images: one byte a pixel (mono8)."""
    camera = FisheyeCamera.default()
    return camera.width, camera.height


def prerender_bytes(scene: Scene) -> int:
    """Memory the images of ``scene`` take once prerendered, bytes: one (H, W) uint8 image a frame, at the
    simulator's camera size (640x480: 307 kB a frame, 9.2 MB per second of scene at 30 fps)."""
    width, height = _image_size()
    return scene.n_frames * width * height


def _check_prerender(name: str, scene: Scene, max_mb: float) -> None:
    """ValueError naming the scene ``name``, its frames and size when its prerendered images would take more
    than ``max_mb`` MB (1 MB = 1e6 bytes)."""
    need = prerender_bytes(scene)
    if need <= max_mb * 1e6:
        return
    width, height = _image_size()
    frame = need // scene.n_frames
    raise ValueError(f"{name}: prerender would hold its {scene.n_frames:,} frames ({scene.duration_s:g} s at "
                     f"{scene.fps:g} fps) as {width}x{height} images of {frame / 1e3:.0f} kB: "
                     f"{need / 1e6:,.0f} MB, over prerender_max_mb {max_mb:g} (room for {int(max_mb * 1e6 // frame):,} "
                     f"frames, {max_mb * 1e6 / frame / scene.fps:.3g} s of this scene); play it without prerender, "
                     "shorten it or raise prerender_max_mb")


def read_scene(scene_path: str, prerender: bool = False, check_frames: int = 0,
               prerender_max_mb: float | None = None) -> Scene | None:
    """The scene of the file ``scene_path`` ("": random scenarios, None); ValueError naming it when it
    cannot be read or is no valid scene, when ``prerender`` comes without one (random scenarios never end)
    or its images would take more than ``prerender_max_mb`` MB (`prerender_bytes`; None: no bound), or when
    one of its first ``check_frames`` frames cannot be played (their mechanics are played first, without
    rendering: `fv_algos.sim.sensor.check_scene`, 0.7 to 5.5 ms a frame). The camera's params call it, so
    `fv launch --check` and the launch itself refuse what the source would meet: a camera whose scene slid
    its object off the skin at frame 34 replayed frames 0 to 33 for good; one prerendering a 600 s scene
    rendered for 6 minutes and held 5.5 GB before its first frame. The check is bounded (the
    camera's `scene_check_frames`: a whole 18,000-frame scene took 14 s) and made once per launch
    (`nodes.launch_checks`: the launcher makes it, its camera, respawned too, skips a scene of the same
    content); a later frame that cannot be played stops the camera as it comes."""
    name = source_name(scene_path)
    if prerender and not scene_path:
        raise ValueError(f"{name}: prerender needs a scene file (random scenarios never end)")
    try:
        scene = load_scene(scene_path) if scene_path else None
    except (OSError, ValueError) as exc:
        raise ValueError(f"sim {exc}") from None  # load_scene's message starts with the path
    if scene is None:
        return None
    if prerender and prerender_max_mb is not None:
        _check_prerender(name, scene, prerender_max_mb)
    if check_frames and not launch_checks.passed(key := _check_key(scene, check_frames)):
        try:
            check_scene(scene, frames=check_frames)
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from None
        launch_checks.note_passed(key)
    return scene


def _check_key(scene: Scene, frames: int) -> str:
    """The `launch_checks` key of playing the first ``frames`` frames of ``scene``: a digest of its content
    (its effects sorted: a set's order differs between processes) and of ``frames``."""
    content = repr(dataclasses.replace(scene, effects=tuple(sorted(scene.effects))))
    return f"sim-scene:{frames}:{hashlib.sha256(content.encode()).hexdigest()}"


class SimSource:
    """Frames of the simulated sensor: a scene file played in a loop, or endless random
    scenarios (`scene_path` ""). `camera` is the simulator's exact fisheye model.

    With `prerender`, open() renders the whole scene once and read() replays its images from
    memory (only those: not the frames' ground truth, which the camera does not publish), so the
    camera costs what a real camera's driver costs: how `fv bench pipeline` measures the pipeline
    rather than the renderer. That holds one 307 kB image a frame at 640x480 (`prerender_bytes`): open()
    kept 9.5 MB per second of scene at 30 fps (launch/scenes, traced), and renders them all before the first
    frame; the camera's params bound it (`prerender_max_mb`). It needs a scene file (random scenarios never end)."""

    def __init__(self, scene_path: str, seed: int, fps: float, prerender: bool = False,
                 scene: Scene | None = None) -> None:
        """`scene`: the scene of `scene_path` read already (`read_scene`: the camera's params read and check it),
        or None to read it here."""
        self.scene_path = scene_path
        self.seed = seed
        self.fps = fps
        self.prerender = prerender
        self.name = source_name(scene_path)
        if scene is None:
            try:
                scene = read_scene(scene_path, prerender)
            except ValueError as exc:
                raise SourceError(str(exc)) from None
        self.sensor = SimSensor(scene, seed=seed, loop_fps=fps)
        self.camera = self.sensor.camera
        self._images: Iterator[np.ndarray] | None = None
        self._rendered: list[np.ndarray] | None = None  # with prerender: the scene's (H, W) uint8 images

    def open(self) -> None:
        """Start the scene (or the random scenarios) from its first frame; with `prerender`, render it
        first. SourceConfigError as `read`."""
        if self.prerender and self._rendered is None:
            scene = self.sensor.scene
            log.info("%s: rendering its %d frames (%.0f MB) before the first is published (prerender)", self.name,
                     scene.n_frames, prerender_bytes(scene) / 1e6)  # 10 to 20 s within the default bound
            started = time.monotonic()
            try:
                self._rendered = [frame.image for frame in self.sensor]
            except ValueError as exc:
                raise SourceConfigError(f"{self.name}: {exc}") from None
            log.info("%s: rendered in %.1f s", self.name, time.monotonic() - started)
        self._images = iter(self._rendered) if self._rendered is not None else (frame.image for frame in self.sensor)

    def read(self) -> Frame | None:
        """The next frame (after the last, the first again). A frame the mechanics cannot play (e.g. the
        object slid off the skin) raises SourceConfigError for a scene file, which would meet it again at
        every pass, and SourceError in random scenarios, where reopening plays the next scenario."""
        if self._images is None:
            return None
        try:
            image = next(self._images, None)
            if image is None:  # a scene ended: play it again
                self.open()
                image = next(self._images)
        except ValueError as exc:
            error = SourceError if self.sensor.scene is None else SourceConfigError
            raise error(f"{self.name}: {exc}") from None
        return Frame(image, time.time_ns())

    def close(self) -> None:
        self._images = None
