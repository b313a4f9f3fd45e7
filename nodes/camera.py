"""The `camera` node: frames from the simulator, a video file, a folder of images or a
V4L2 device, published as `Image` on `/camera/image` with capture stamps, plus a latched
`CameraInfo` on `/camera/info`. `crop` and `size` cut a share off each border of every frame
and resize the rest (after `undistort`; `CameraInfo` describes the frames as published); a crop that
leaves nothing of the source's frames is refused at start, the frame size named. A
`calibration` made at another resolution of the same aspect ratio is scaled to the source's
frames (logged once); one of another aspect ratio is refused at start, both sizes named. A
lost source is reported in NodeStatus and reopened with backoff; a source that cannot be
opened at start fails with a clear error: a V4L2 camera not there yet with exit code TEMPFAIL (a
launch starts it again until it is plugged in), any other source with CONFIG (`nodes.exit_codes`). So
does, with CONFIG, one that can give no further frame as configured (a simulated scene that cannot
play its next frame), said in NodeStatus first.

A video or folder source numbers its frames from 0 at each pass (`Image.frame_index`); at each pass's first frame
(frame 0, or the first a folder could read) the camera also says, latched on `camera/pass_start`, that its source
started over (`msgs.GraspStart`, cause "source restart", stamped as that frame): a tracker respawned as the pass
began resumes no reference of the pass before.

`start_after` holds the first frame back until the named nodes have reported
(`nodes.start_gate.StartGate`: a NodeStatus sent since the camera started, once their
subscriptions are made), so that a replayed video reaches them whole from its first frame;
after `start_timeout_s` it starts anyway, warned."""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from fv_algos.fisheye import FisheyeCamera
from fv_algos.frame_crop import FrameCrop
from msgs import CameraInfo, GraspStart, Image
from msgs.camera import source_started_over
from nodes.camera_sources import (FolderSource, Frame, FrameSource, SourceConfigError, SourceError, V4L2Source,
                                  VideoFileSource)
from nodes.client import PASS_START_TOPIC
from nodes.node import Node
from nodes.start_gate import StartGate

if TYPE_CHECKING:
    from fv_algos.sim.scene import Scene

SOURCES = ("sim", "video", "folder", "v4l2")
ENCODINGS = ("mono8", "bgr8")


@dataclass
class CameraParams:
    source: str = "sim"  # sim | video | folder | v4l2
    path: str = ""  # video file, image folder, or V4L2 index / device path
    scene: str = ""  # sim: scene file (YAML/JSON); "" = looping random scenarios
    fps: float = 30.0  # publish rate in Hz (video: 0 = the file's own rate)
    loop: bool = True  # video / folder: start again at the end
    width: int = 640  # v4l2 capture size (px); 0 = the camera's own
    height: int = 480
    exposure: float = -1.0  # v4l2 manual exposure (driver units), < 0 = auto
    white_balance: float = -1.0  # v4l2 white balance temperature (K), < 0 = auto
    calibration: str = ""  # calibration JSON from `fv calibrate` ("" = none / sim's own); scaled to another resolution
    undistort: bool = False  # remap frames with the calibration before publishing
    crop: list[float] = field(default_factory=list)  # shares cut off the borders: [] none, [s] each, [top, bottom, left, right]
    size: list[int] = field(default_factory=list)  # [width, height] px the cropped frame is resized to ([] = as cut)
    encoding: str = "mono8"  # mono8 | bgr8
    seed: int = 0  # sim: random seed
    prerender: bool = False  # sim: render the scene once at start and replay it from memory
    prerender_max_mb: float = 500.0  # sim with prerender: most memory (MB) the scene's images may take (307 kB a
    # frame at 640x480: 500 MB is 1,627 frames, 54 s at 30 fps); a longer scene is refused at start
    scene_check_frames: int = 600  # sim: frames of the scene's mechanics played to check it before it starts, once
    # per launch (`nodes.launch_checks`; 0: none); a longer scene's later frames are checked as they play (a frame
    # it cannot play stops the launch)
    frame_id: str = "fv_camera"
    reopen_backoff_s: float = 0.5  # first retry delay after a lost source; doubles up to 8 s
    start_after: list[str] = field(default_factory=list)  # node names to wait for before the first frame
    start_timeout_s: float = 30.0  # start anyway (warned) when they have not all reported by then
    exit_after_end_s: float = -1.0  # video / folder played once: exit (status 0) this long after its last frame,
    # time for the pipeline to judge it, so that a launch replaying a file ends (< 0: keep running)

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"source {self.source!r} is not one of {SOURCES}")
        if self.encoding not in ENCODINGS:
            raise ValueError(f"encoding {self.encoding!r} is not one of {ENCODINGS}")
        if self.fps < 0 or (self.fps == 0 and self.source != "video"):
            raise ValueError(f"fps {self.fps} must be > 0 (0 only for a video's own rate)")
        if self.source in ("video", "folder", "v4l2") and not self.path:
            raise ValueError(f"source {self.source!r} needs a path")
        if self.source in ("video", "folder"):  # refused before a launch starts (fv launch --check)
            self.path = str(Path(self.path).expanduser())  # a shell leaves the ~ of video:=~/clip.avi as it is
            if not (Path(self.path).is_file() if self.source == "video" else Path(self.path).is_dir()):
                raise ValueError(f"{self.source} {self.path}: no such {'file' if self.source == 'video' else 'folder'}")
        self.sim_scene: Scene | None = None  # not a param: the scene read from `scene` here, which the source plays
        if self.source == "sim":  # a missing or bad scene, or one it cannot play: refused before a launch starts
            from nodes.sim_source import read_scene
            self.scene = str(Path(self.scene).expanduser()) if self.scene else ""
            if self.scene_check_frames < 0:
                raise ValueError(f"scene_check_frames {self.scene_check_frames} must be >= 0")
            if self.prerender_max_mb <= 0:
                raise ValueError(f"prerender_max_mb {self.prerender_max_mb} must be > 0")
            self.sim_scene = read_scene(self.scene, self.prerender, self.scene_check_frames, self.prerender_max_mb)
        if self.undistort and not self.calibration and self.source != "sim":
            raise ValueError("undistort needs a calibration file")
        if self.start_timeout_s < 0:
            raise ValueError(f"start_timeout_s {self.start_timeout_s} must be >= 0")
        if self.width < 0 or self.height < 0 or (self.width == 0) != (self.height == 0):
            raise ValueError(f"capture size {self.width}x{self.height}: both > 0, or both 0 for the camera's own")
        FrameCrop.from_lists(self.crop, self.size)  # ValueError names a bad crop or size


def make_source(p: CameraParams) -> FrameSource:
    """The frame source the params ask for (not opened yet)."""
    if p.source == "video":
        return VideoFileSource(p.path, p.loop)
    if p.source == "folder":
        return FolderSource(p.path, p.loop)
    if p.source == "v4l2":
        return V4L2Source(p.path, p.width, p.height, p.fps, p.exposure, p.white_balance)
    from nodes.sim_source import SimSource
    return SimSource(p.scene, p.seed, p.fps, p.prerender, scene=p.sim_scene)  # the file read once, by the params


RATE_CHECK_S = 5.0  # the stretch of published frames the camera's rate is checked over, s
RATE_SHORT = 0.75  # a stretch below this share of the rate asked for is warned of (not a busy second)


class CameraNode(Node):
    """Publishes frames at `fps` from the configured source."""

    Params = CameraParams

    def setup(self) -> None:
        p = self.params
        self.source = make_source(p)
        self.source.open()  # SourceError at start is fatal, with the source named (SourceMissing: not yet)
        self.image_pub = self.publisher("camera/image", Image)
        self.info_pub = self.publisher("camera/info", CameraInfo, latched=True)
        numbered = p.source in ("video", "folder")  # sources whose frames are numbered, pass by pass
        self.pass_pub = self.publisher(PASS_START_TOPIC, GraspStart, latched=True) if numbered else None
        self.last_index = -1  # frame_index of the frame published last (-1: none yet, or a live source's)
        self.held_frame: Frame | None = None  # read at setup for its size, published first
        self.end_at: float | None = None  # monotonic time to stop at, once the source has ended
        self.fisheye = self._load_calibration()
        self.maps = self.fisheye.undistort_maps() if (p.undistort and self.fisheye) else None
        self.crop = FrameCrop.from_lists(p.crop, p.size)
        if self.crop is not None:  # a crop that leaves nothing of the frames: refused at start, not every frame
            height, width = self._first_frame("checking the crop").image.shape[:2]
            self.crop.window(width, height)
        if p.source in ("video", "folder"):  # one without a frame (an empty video) is refused at start
            self._first_frame("playing it")
        self._publish_info()
        rate = p.fps or getattr(self.source, "file_fps", 0.0) or 30.0
        self.rate_hz = rate
        self.backoff_s = 0.0
        self.retry_at = 0.0
        self.stretch: tuple[float, int] | None = None  # (monotonic s, frames published since) of the rate check
        self.slow_message = ""  # the below-rate warning while it stands
        self.counters.update(frames=0, lost=0, reopened=0, below_rate=0)
        self.start_gate = StartGate(self, p.start_after, p.start_timeout_s)
        self.timer(1.0 / rate, self.tick)

    def _load_calibration(self) -> FisheyeCamera | None:
        """The calibration file's camera fitted to the source's frames (`FisheyeCamera.for_size`, with
        the size of a first frame read here and held to be published first), the simulator's own
        camera, or None.

        Raises:
            ValueError: the calibration file is bad, or of another aspect ratio than the frames.
            SourceError: the source gives no first frame.
        """
        if not self.params.calibration:
            return getattr(self.source, "camera", None)
        camera = FisheyeCamera.load(self.params.calibration)
        height, width = self._first_frame(f"checking the calibration's {camera.width}x{camera.height}") \
            .image.shape[:2]
        fitted = camera.for_size(width, height)
        if fitted is not camera:
            self.log.warning("calibration %s is for %dx%d frames: its matrix is scaled by %.3g to the source's "
                             "%dx%d frames", self.params.calibration, camera.width, camera.height,
                             width / camera.width, width, height)
        return fitted

    def _first_frame(self, need: str) -> Frame:
        """The source's first frame, read once and held to be published first; SourceError when the
        source gives none (``need`` names what needed it)."""
        if self.held_frame is None:
            self.held_frame = self.source.read()
            if self.held_frame is None:
                raise SourceError(f"{self.source.name}: no frame, and {need} needs one")
        return self.held_frame

    def _publish_info(self) -> None:
        """The camera model of the frames as published: undistorted frames are a pinhole camera
        (the undistorted matrix, no distortion), cropped and resized ones a moved, scaled one."""
        cam = self.fisheye
        if cam is None:
            return
        K, D = np.asarray(cam.K, np.float64), np.asarray(cam.D, np.float64).reshape(4)
        model = "fisheye"
        if self.maps is not None:  # a fisheye model with D = 0 would be equidistant: 128 px off at a corner
            K, D, model = cam.undistorted_camera_matrix(), np.zeros(4), "pinhole"
        width, height = cam.width, cam.height
        if self.crop is not None:
            K, width, height = self.crop.camera_matrix(K, width, height)
        self.info_pub.publish(CameraInfo(stamp_ns=time.time_ns(), frame_id=self.params.frame_id, model=model,
                                         width=width, height=height, K=K, D=D, rms_px=float(getattr(cam, "rms_px", 0.0) or 0.0)))

    def tick(self) -> None:
        if getattr(self.source, "finished", False):
            self._after_end()
            return
        if self.start_gate.waiting():
            return
        if self.retry_at:
            if time.monotonic() < self.retry_at:
                return
            self._reopen()
            return
        held, self.held_frame = self.held_frame, None
        try:  # the held frame is stamped now, when it is played: it was read before the start gate opened
            frame = replace(held, stamp_ns=time.time_ns()) if held is not None else self.source.read()
        except SourceConfigError as exc:  # every reopening would meet it again
            self.fail(str(exc))
            return
        except SourceError as exc:
            self._lost(str(exc))
            return
        if frame is None:
            if getattr(self.source, "finished", False):
                self._ended()
                self._after_end()
                return
            self._lost(f"{self.source.name}: no frame")
            return
        self.publish_frame(frame)

    def _ended(self) -> None:
        """Say that the source has ended: a line of information at its end, a warning when a video's decoding
        stopped before the frames its container lists (a file cut short or damaged)."""
        said = f"{self.source.name}: end of input after {self.counters['frames']} frames"
        missing = getattr(self.source, "missing_frames", 0)
        if missing:
            self.warn(f"{said}, {missing} fewer than the file lists (cut short or damaged?)")
        else:
            self.log.info(said)

    def _after_end(self) -> None:
        """Once the source has ended: stop the node `exit_after_end_s` after its last frame (when >= 0)."""
        if self.params.exit_after_end_s < 0:
            return
        now = time.monotonic()
        if self.end_at is None:
            self.end_at = now + self.params.exit_after_end_s
        elif now >= self.end_at:
            self.log.info("%s has ended (exit_after_end_s %g): stopping", self.source.name,
                          self.params.exit_after_end_s)
            self.stop()

    def _lost(self, why: str) -> None:
        """Report the source lost (`why` names it: a SourceError's text) and retry with
        backoff; counters["lost"] counts losses, not the failed retries that follow."""
        if not self.retry_at:
            self.counters["lost"] += 1
        self.stretch = None  # the time lost is no measure of the rate
        self.backoff_s = min(8.0, max(self.params.reopen_backoff_s, 2 * self.backoff_s))
        self.retry_at = time.monotonic() + self.backoff_s
        self.warn(f"{why}; reopening in {self.backoff_s:.1f} s")
        self.source.close()

    def _reopen(self) -> None:
        try:
            self.source.open()
        except SourceError as exc:
            self._lost(str(exc))
            return
        self.retry_at = 0.0
        self.backoff_s = 0.0
        self.counters["reopened"] += 1
        self.clear_warning()
        self._publish_info()

    def publish_frame(self, frame: Frame) -> None:
        image = frame.image
        if self.params.encoding == "mono8" and image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        elif self.params.encoding == "bgr8" and image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if self.maps is not None:
            image = cv2.remap(image, self.maps[0], self.maps[1], cv2.INTER_LINEAR)
        if self.crop is not None:
            image = self.crop.apply(image)
        if self.pass_pub is not None and frame.index >= 0 and (
                self.last_index < 0 or source_started_over(frame.index, self.last_index)):
            # a pass's first frame (its frame 0, or the first that could be read: a folder's), said before the
            # frame, which a tracker may take as it comes
            self.pass_pub.publish(GraspStart(stamp_ns=frame.stamp_ns, frame_id=self.params.frame_id,
                                             cause="source restart"))
        self.last_index = frame.index
        self.image_pub.publish(Image(stamp_ns=frame.stamp_ns, frame_id=self.params.frame_id,
                                     encoding=self.params.encoding, data=np.ascontiguousarray(image),
                                     frame_index=frame.index))
        self.counters["frames"] += 1
        self._check_rate(time.monotonic())

    def _check_rate(self, now_s: float) -> None:
        """After a frame published at `now_s` (monotonic s): over every `RATE_CHECK_S` of frames, warn when
        fewer came than `RATE_SHORT` of the rate asked for (a renderer, decoder or driver slower than `fps`:
        the camera fell behind without a word, its status "ok"), counted in `below_rate`; the warning
        clears once a stretch keeps the rate."""
        if self.stretch is None:
            self.stretch = (now_s, 0)
            return
        start_s, frames = self.stretch[0], self.stretch[1] + 1
        elapsed_s = now_s - start_s
        if elapsed_s < RATE_CHECK_S:
            self.stretch = (start_s, frames)
            return
        self.stretch = (now_s, 0)
        measured = frames / elapsed_s
        if measured < RATE_SHORT * self.rate_hz:
            self.counters["below_rate"] += 1
            self.slow_message = (f"{self.source.name}: {measured:.1f} frames/s over {elapsed_s:.1f} s, below the "
                                 f"{self.rate_hz:g} asked for (fps): a frame takes longer than 1/fps to read and "
                                 "publish (below_rate)")
            self.warn(self.slow_message, kind="below rate")
        elif self.slow_message:
            if self.message == self.slow_message:
                self.clear_warning()
            self.slow_message = ""

    def teardown(self) -> None:
        if hasattr(self, "source"):
            self.source.close()
