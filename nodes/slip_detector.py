"""The `slip_detector` node: DisplacementField -> SlipState on `/slip` at the field rate.

A window model keeps the last `window` fields (the model's window length), asks the
ConvLSTM for P(slip), and decides with a threshold and optional hysteresis. Its fields are
rescaled from the camera's frame width (the tracker's `/markers/reference`, latched) to that of the
frames it was trained on (`ModelConfig.field_width_px`); until that width is known no window is
judged (counted in no_width). Every field
enters the window, but when the model falls behind (newer fields already queued) only the
newest window is judged: the skipped decisions are counted, and latency stays one model call.

A trial model (`gelsight_online`, `gelsight_trial`) judges the whole grasp so far: a grasp
starts at the tracker's reference (`/markers/reference`, latched: a new one after
`/tracker/reset`), and every field of it, with the camera image of the same stamp (`/camera/image`), updates the
running P(slip) of the grasp (`fv_algos.grasp_judge`); a field stamped before the grasp's reference (none
yet, or one of the grasp before) is left out, counted in before_grasp. A new reference takes over at its
grasp's first field: the fields of the grasp before that come after it (the reference comes straight from the
tracker, a frame's field through the interpolator, so it may overtake the last ones) are judged in that grasp,
and several references that come before their first fields take over in turn; the grasp's own reference
message again (the same stamp: a respawned tracker's, which publishes the reference it resumes as it was
taken) starts none, and one stamped before it (a recording played again) starts its
grasp at once. Its SlipState's window_stamps_ns
holds the grasp's first stamp and that of its last frame judged: a camera faster than the model's
frame rate (`fv_algos.frame_rate`) has only the frames a camera at that rate would have filmed judged,
and the others repeat the grasp's P(slip) so far (counted in rate_skipped). That answer is the grasp's outcome so far, to be
read at the end of a test motion with `gelsight_trial`, which early in a grasp often says slip;
`gelsight_online` was also trained on the beginnings of held grasps, so its P(slip) starts low
(README, real sensors).
It was trained from frame `reference_frame` of each recording on (logged at start): the
tracker's `reference_frame` should be the same (launch/video.yaml does so).

`model` is a shipped model name (`sim_cnn_lstm`: per-field CNN then LSTM, the default and
the fastest; `sim_fast`: the ConvLSTM with 16 hidden channels; `sim`: the paper's ConvLSTM;
`gelsight_trial` (also named `gelsight`) and `gelsight_online`: the trial models for GelSight
Mini-class sensors; `gelsight_windows`: the paper's ConvLSTM trained on real GelSight Mini grasps,
at chance on unseen objects) or a checkpoint path."""
from __future__ import annotations

import collections
import re
import zipfile
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from fv_algos.visualize import as_bgr
from msgs import DisplacementField, Image, MarkerArray, SlipState
from nodes.node import Node
from nodes.params import build_params
from nodes.shipped_models import model_path

if TYPE_CHECKING:  # torch is imported only where a model is used
    from fv_algos.trial_net import TrialModel

DEVICE_RE = re.compile(r"cpu|mps|(cuda|xpu)(:\d+)?")  # the torch devices a model can run on
IMAGE_BUFFER = 64  # camera images kept for the fields still to come (trial models), frames


def require_grid(msg: DisplacementField, grid: tuple[int, int]) -> None:
    """ValueError naming both grids when the field of `msg` is not on the model's `grid` (rows, columns)."""
    if msg.field.shape[:2] != grid:
        raise ValueError(f"field grid {msg.field.shape[:2]} does not match the model's {grid[0]}x{grid[1]}: "
                         "set the interpolator's grid param")


@dataclass
class SlipDetectorParams:
    model: str = "sim_cnn_lstm"  # shipped model name (the module docstring lists them) or checkpoint path
    threshold: float = 0.5  # P(slip) above which the state is slip
    hysteresis: float = 0.0  # slip turns on above threshold + h and off below threshold - h
    threads: int = 1  # torch threads for inference
    device: str = "cpu"  # cpu | cuda | cuda:N | mps | xpu | xpu:N (a window model; a trial model runs on the cpu)
    input_timeout_s: float = 2.0  # warn in NodeStatus after this long without a field (0 = never)
    window_gap_s: float = 1.0  # window model: a field stamped before the last or this long after it starts a new window

    def __post_init__(self) -> None:
        if not 0.0 < self.threshold < 1.0:
            raise ValueError(f"threshold {self.threshold} must be in (0, 1)")
        if not 0.0 <= self.hysteresis < min(self.threshold, 1.0 - self.threshold):
            raise ValueError(f"hysteresis {self.hysteresis} must be >= 0 and keep threshold +/- h inside (0, 1)")
        if self.threads < 1:
            raise ValueError(f"threads {self.threads} must be >= 1")
        if not DEVICE_RE.fullmatch(self.device):  # checked by name: torch is not imported for a cpu launch
            raise ValueError(f"device {self.device!r} is not cpu, cuda, cuda:N, mps, xpu or xpu:N")
        if self.device != "cpu":  # one this torch cannot use is refused by `fv launch --check`, not respawned
            from fv_algos.slip.models import usable_device
            usable_device(self.device)
        if self.input_timeout_s < 0:
            raise ValueError(f"input_timeout_s {self.input_timeout_s} must be > 0, or 0 for never")
        if self.window_gap_s <= 0:
            raise ValueError(f"window_gap_s {self.window_gap_s} must be > 0")
        try:  # a misspelt model is refused before a launch starts (fv launch --check), not respawned for good
            path = model_path(self.model)
        except FileNotFoundError as exc:
            raise ValueError(str(exc)) from None
        if not zipfile.is_zipfile(path):  # as is a file that is none: the .json beside a trained model was
            raise ValueError(f"model {self.model!r}: {path} is not a model file (torch.save writes a zip "
                             "archive; give the .pt)")  # respawned for good, the camera waiting for it


def load_model(p: SlipDetectorParams) -> tuple[TrialModel | None, Any, float]:
    """The model `p.model` names, as (trial model, None, 0.0), or as (None, window `SlipClassifier` on
    `p.device` with `p.threads`, the wall time in s of the first pass it has run)."""
    from fv_algos.slip.classifier import SlipClassifier
    from fv_algos.trial_net import read_trial_model
    path = model_path(p.model)
    trial_model = read_trial_model(path)
    if trial_model is not None:
        return trial_model, None, 0.0
    classifier = SlipClassifier(path, device=p.device, threads=p.threads)
    return None, classifier, classifier.warm_up()


class SlipDetectorNode(Node):
    """Publishes a slip decision per field: from a sliding window, or from the grasp so far."""

    Params = SlipDetectorParams
    LIVE_PARAMS = frozenset({"threshold", "hysteresis"})  # read by each decision (`fv param set`)
    # a standby process's window model, loaded and run once before it takes over: (model, device,
    # threads) it was loaded for, the classifier, its first pass in s
    prepared: ClassVar[tuple[tuple[str, str, int], Any, float] | None] = None

    @classmethod
    def preload(cls, params: dict[str, Any]) -> None:
        """Import torch and, for a window model, load it and run its first pass: a spare that did this at
        takeover left `/slip` silent 0.94 s after a `kill -9` of the slip detector (30 fps)."""
        p = build_params(cls.Params, params, where="slip_detector standby")
        _, classifier, warm_up_s = load_model(p)
        if classifier is not None:
            cls.prepared = ((p.model, p.device, p.threads), classifier, warm_up_s)

    def setup(self) -> None:
        p = self.params
        self.slip = False
        self.slip_pub = self.publisher("slip", SlipState)
        self.counters.update(decisions=0, invalid_windows=0, skipped=0, empty_references=0)
        prepared, type(self).prepared = type(self).prepared, None
        if prepared is not None and prepared[0] == (p.model, p.device, p.threads):
            trial_model, classifier, warm_up_s = None, prepared[1], prepared[2]
        else:
            trial_model, classifier, warm_up_s = load_model(p)
        if trial_model is not None:
            self.setup_grasp(trial_model)
        else:
            self.setup_window(classifier, warm_up_s)

    def setup_window(self, classifier: Any, warm_up_s: float) -> None:
        """Judge windows of fields with `classifier` (a `SlipClassifier` whose first pass took `warm_up_s`)."""
        p = self.params
        self.classifier = classifier
        cfg = self.classifier.config
        self.window: collections.deque = collections.deque(maxlen=cfg.window)
        self.frame_width_px: int | None = None  # of the tracker's reference frame
        self.counters.update(no_width=0, window_restarts=0, duplicate_fields=0)
        if cfg.field_width_px:
            self.subscribe("markers/reference", MarkerArray, self.on_window_reference, depth=1)
        self.field_sub = self.subscribe("field", DisplacementField, self.on_field, depth=cfg.window,
                                        stale_after_s=p.input_timeout_s or None, answered_by=self.slip_pub)
        self.log.info("model %s: window %d, grid %d, fields read at %s px wide frames; on %s, first pass %.0f ms",
                      p.model, cfg.window, cfg.grid, cfg.field_width_px or "any", p.device, 1e3 * warm_up_s)

    def setup_grasp(self, model: TrialModel) -> None:
        import torch

        from fv_algos.grasp_judge import GraspJudge
        from fv_algos.real_trials import FIELD_GRID
        p = self.params
        if p.device != "cpu":
            raise ValueError(f"a trial model runs on the cpu only, not device {p.device!r}")
        torch.set_num_threads(p.threads)
        self.judge = GraspJudge(model.net, model.params, model.fps, model.stretch)
        self.field_grid = FIELD_GRID  # (rows, columns) of the fields the model reads
        self.judged: tuple[float, int] | None = None  # P(slip) of the grasp at its last frame judged, and that stamp
        self.images: collections.OrderedDict[int, Image] = collections.OrderedDict()  # by stamp, oldest first
        self.grasp_start_ns: int | None = None
        self.next_grasps: dict[int, int] = {}  # reference stamp -> markers of grasps to take over at their first fields
        self.first_field_ns: int | None = None  # stamp of the grasp's first field given to the judge
        self.last_field_ns: int | None = None  # stamp of the grasp's last field given to the judge
        self.reference_markers = 0
        self.slow_gaps_before = 0  # the judge's slow gaps before the current grasp
        self.subscribe("camera/image", Image, self.on_image, depth=IMAGE_BUFFER)
        self.subscribe("markers/reference", MarkerArray, self.on_reference, depth=1)
        self.subscribe("field", DisplacementField, self.on_grasp_field, depth=IMAGE_BUFFER,
                       stale_after_s=p.input_timeout_s or None, answered_by=self.slip_pub)
        self.counters.update(grasps=0, before_grasp=0, unmatched_fields=0, rate_skipped=0, slow_gaps=0,
                             out_of_order_fields=0)
        self.log.info("model %s: trial model, judges each grasp from the tracker's reference on (trained with "
                      "the reference at frame %d of each video: give the tracker reference_frame %d), at %g fps "
                      "(a faster camera's frames are picked at that rate)",
                      p.model, model.reference_frame, model.reference_frame, model.fps)

    def decide(self, probability: float) -> None:
        """Update the slip state with threshold and hysteresis (kept between the two bounds)."""
        p = self.params
        if probability > p.threshold + p.hysteresis:
            self.slip = True
        elif probability < p.threshold - p.hysteresis:
            self.slip = False

    def on_window_reference(self, msg: MarkerArray) -> None:
        """The camera's frame width, which the window model's fields are rescaled from (a reference
        without markers is none: see `usable_reference`)."""
        if self.usable_reference(msg):
            self.frame_width_px = msg.width

    def usable_reference(self, msg: MarkerArray) -> bool:
        """False, with a warning and counted in empty_references, for a reference without markers (a
        camera that saw no skin, or a message from elsewhere): it gives no grasp to judge, and its width
        no frame width (the decoder refuses a width <= 0)."""
        if len(msg.ref_px):
            return True
        self.counters["empty_references"] += 1
        self.warn(f"a /markers/reference without markers from {msg.node!r} ignored (empty_references)")
        return False

    def on_field(self, msg: DisplacementField) -> None:
        """Window model: add the field to the window and judge the window once it holds `cfg.window` fields.
        ValueError for a field of another grid than the model's; a field stamped as the last is dropped
        (duplicate_fields); one stamped before the last or more than window_gap_s after it starts a new
        window (window_restarts)."""
        cfg = self.classifier.config
        require_grid(msg, (cfg.grid, cfg.grid))
        gap_ns = msg.stamp_ns - self.window[-1][0] if self.window else None
        if gap_ns == 0:  # the same frame again (two publishers on one topic): it would count twice in the window
            self.counters["duplicate_fields"] += 1
            self.warn(f"a field from {msg.node!r} stamped as the last field dropped (duplicate_fields)",
                      kind="duplicate field")
            return
        if gap_ns is not None and not 0 < gap_ns <= self.params.window_gap_s * 1e9:
            # not the next field of the window's stream (a bag replayed again, a stale field): a window of it
            # would span that gap, with its stamps out of order
            self.counters["window_restarts"] += 1
            self.warn(f"field stamped {gap_ns / 1e9:+.9g} s from the last (window_gap_s {self.params.window_gap_s:g} "
                      "s): a new window starts (window_restarts)", kind="window restart")
            self.window.clear()
        self.window.append((msg.stamp_ns, msg.field, msg.valid))
        if len(self.window) < self.window.maxlen:
            return
        if self.field_sub.queue:  # newer fields wait: judge only the newest window (latency stays one call)
            self.counters["skipped"] += 1
            return
        if cfg.field_width_px and self.frame_width_px is None:
            self.counters["no_width"] += 1
            self.warn("no frame width from the tracker's /markers/reference yet: the model reads fields in px of "
                      f"{cfg.field_width_px} px wide frames, so windows wait for it (no_width)")
            return
        stamps = np.array([s for s, _, _ in self.window], np.int64)
        valid = all(v for _, _, v in self.window)
        probability = 0.0
        if valid:
            try:
                probability = self.classifier.predict(np.stack([f for _, f, _ in self.window]), self.frame_width_px)
            except ValueError as exc:  # non-finite field values: flag the window, keep running
                self.warn(f"window rejected: {exc}", kind="window rejected")
                valid = False
        if valid:
            self.clear_warning()  # a window judged: whatever was wrong before is over
            self.decide(probability)
        else:
            self.counters["invalid_windows"] += 1
        self.publish_state(msg, probability, stamps, valid)

    def on_image(self, msg: Image) -> None:
        self.images[msg.stamp_ns] = msg
        while len(self.images) > IMAGE_BUFFER:
            self.images.popitem(last=False)

    def on_reference(self, msg: MarkerArray) -> None:
        """A new reference (not one without markers): a new grasp starts at its frame. One stamped after the
        grasp under way's start takes over at the first field stamped at or after it (`next_grasps`): the grasp
        under way keeps the fields stamped before it, which the reference may have overtaken. One stamped before
        it (time went back: a recording played again) takes over at once, as does the first; the reference of
        the grasp under way (its stamp) starts none."""
        if not self.usable_reference(msg):
            return
        if self.grasp_start_ns is None or msg.stamp_ns < self.grasp_start_ns:
            self.next_grasps.clear()
            self.grasp_start_ns, self.reference_markers = msg.stamp_ns, len(msg.ref_px)
            self.start_grasp()
        elif msg.stamp_ns != self.grasp_start_ns:
            self.next_grasps[msg.stamp_ns] = len(msg.ref_px)

    def start_grasp(self) -> None:
        """Judge the grasp from its reference frame (`grasp_start_ns`) on, from nothing."""
        self.slow_gaps_before = self.judge.slow_gaps
        self.judge.reset()
        self.judged = None
        self.first_field_ns = self.last_field_ns = None
        self.slip = False
        self.counters["grasps"] += 1

    def on_grasp_field(self, msg: DisplacementField) -> None:
        """Trial model: judge the grasp so far with the field and the camera image of its stamp, and publish
        its P(slip). ValueError for a field of another grid than `real_trials.FIELD_GRID`; left out and
        counted: a field before the grasp's reference (before_grasp), one stamped at or before the grasp's
        last field (out_of_order_fields), one without its image (unmatched_fields); ValueError for mono8 images.
        A field stamped at or before the grasp's first one judged, after later ones, is the recording played
        again (`fv bag play --loop` of a recording whose frames carry no `frame_index`): the grasp is judged
        again from it, as a new grasp (its fields were all left out as out of order). That first field is the
        reference frame's, or, where the recording began after the tracker took its reference (which the
        replay's tracker resumes, stamped before the recording), the recording's first."""
        require_grid(msg, self.field_grid)
        due = [stamp for stamp in self.next_grasps if stamp <= msg.stamp_ns]
        if due:  # the latest reference at or before this field's frame; those before it had no field
            self.grasp_start_ns = max(due)
            self.reference_markers = self.next_grasps[self.grasp_start_ns]
            for stamp in due:
                del self.next_grasps[stamp]
            self.start_grasp()
        if self.grasp_start_ns is None or msg.stamp_ns < self.grasp_start_ns:
            self.counters["before_grasp"] += 1  # no reference yet, or a field of the grasp before the current one
            return
        if self.first_field_ns is not None and msg.stamp_ns <= self.first_field_ns:
            self.log.info("the grasp's first frame again (a recording played again): its grasp is judged anew")
            self.start_grasp()
        if self.last_field_ns is not None and msg.stamp_ns <= self.last_field_ns:  # judged after it, out of order
            self.counters["out_of_order_fields"] += 1
            self.warn(f"a field stamped {(msg.stamp_ns - self.last_field_ns) / 1e9:+.9g} s from the grasp's last left "
                      "out (out_of_order_fields)", kind="out of order")
            return
        image = self.images.pop(msg.stamp_ns, None)
        while self.images and next(iter(self.images)) < msg.stamp_ns:
            self.images.popitem(last=False)
        if image is None:
            self.counters["unmatched_fields"] += 1
            self.warn("a field without the camera image of its stamp: frame left out of the grasp (unmatched_fields)")
            return
        if not np.isfinite(msg.field).all():
            self.counters["invalid_windows"] += 1
            self.warn("field with non-finite values left out of the grasp")
            return
        if image.encoding == "mono8":
            raise ValueError("the trial model needs colour camera images (bgr8 or rgb8), got mono8: "
                             "set the camera's encoding param")
        if self.first_field_ns is None:
            self.first_field_ns = msg.stamp_ns
        self.last_field_ns = msg.stamp_ns
        takes = self.judge.takes(msg.stamp_ns)
        self.counters["slow_gaps"] = self.judge.slow_gaps
        if self.judge.slow_gaps > self.slow_gaps_before:  # said for the rest of the grasp, whose P(slip) it concerns
            self.warn("frames further apart than the trial model was trained on (a camera slower than the model's "
                      "frame rate, or frames lost): this grasp's P(slip) is less sure (slow_gaps)", kind="slow gaps")
        else:
            self.clear_warning()  # a field the grasp takes: whatever was wrong before is over
        if takes:
            valid_share = msg.n_markers / max(self.reference_markers, 1)
            self.judged = (self.judge.step(as_bgr(image.data, image.encoding), msg.field, valid_share), msg.stamp_ns)
            self.decide(self.judged[0])
        else:  # a camera faster than the model: this frame is not judged, the grasp's P(slip) stands
            self.counters["rate_skipped"] += 1
        probability, judged_ns = self.judged
        self.publish_state(msg, probability, np.array([self.grasp_start_ns, judged_ns], np.int64), True)

    def publish_state(self, msg: DisplacementField, probability: float, stamps: np.ndarray, valid: bool) -> None:
        self.counters["decisions"] += 1
        self.slip_pub.publish(SlipState(stamp_ns=msg.stamp_ns, frame_id=msg.frame_id, probability=probability,
                                        slip=self.slip, threshold=self.params.threshold,
                                        window_stamps_ns=stamps, model=self.params.model, valid=valid))
