"""Trial-level slip classifier: a small temporal network on per-frame descriptors of both cameras.

:func:`camera_descriptors` joins the contact-motion ``SERIES`` of a camera
(:mod:`fv_algos.contact_motion`) and its displacement fields of the same frames into the
``DESCRIPTORS`` (C = 11) per frame, each divided by its ``SCALE`` so that all are of order 1.
:class:`TrialNet` clamps each descriptor to the range it saw in training (a new sensor's values
beyond it cannot push the network further than any training trial did), then reads the
descriptors of each camera with (by default) four dilated 1-D
convolutions (61 frames of context), pools them over time (mean and max, so the trial's length
does not matter), averages the cameras and gives one slip logit per trial (slip when p >= 0.5; no
threshold is tuned); by default it is an ensemble of five such networks, started from different
weights and trained side by side, whose logits are averaged. The decision needs the whole trial
(e.g. when the gripper releases); the series are accumulated online, frame by frame.
"""
from __future__ import annotations

import collections
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from scipy.special import expit
from torch import nn

from fv_algos.contact_motion import ContactMotionParams, TrialSeries
from fv_algos.real_trials import (CAMERAS, FIELD_GRID, Trial, TrialFields, VideoFields, at_reference_width,
                                  require_frames)
from fv_algos.slip.classifier import read_torch_file
from fv_algos.slip.evaluate import classification_metrics
from fv_algos.slip.train import MAX_LR
from fv_algos.trial_eval import fold_summary, map_folds, object_folds

DESCRIPTORS = (
    "relative_px", "marker_px",  # from SERIES, px/frame at size_px scale
    "contact_above_min",  # from SERIES, grey levels
    "field_px", "shear_x_px", "shear_y_px",  # grid means of |d|, dx, dy, px at FIELD_WIDTH_PX
    "invalid_share",  # share of reference markers not valid this frame
    "divergence", "curl",  # grid means of div d and curl d (d in px at FIELD_WIDTH_PX, per grid cell)
    "imprint_change", "imprint_step_rms",  # from SERIES, grey levels
)
SCALE = np.array([1.0, 1.0, 1.0, 5.0, 5.0, 5.0, 0.1, 1 / 3, 1 / 3, 10.0, 1.0], np.float32)
# descriptors that are per-frame rates (divided by the factor a trial is stretched in time by)
PER_FRAME = np.array([n in ("relative_px", "marker_px", "imprint_step_rms") for n in DESCRIPTORS])
# descriptor signs of the image mirrored left-right, and upside down
MIRROR_X = np.array([1, 1, 1, 1, -1, 1, 1, 1, -1, 1, 1], np.float32)
MIRROR_Y = np.array([1, 1, 1, 1, 1, -1, 1, 1, -1, 1, 1], np.float32)
KIND = "trial_net"
MIN_FRAMES = 10  # shortest camera judged, and shortest beginning of a held grasp trained on (0.4 s at 25 fps)
START_FRAMES = 14  # a camera's start-up frames, which start_swap trades (the GelSight Mini burst ends by frame 13)
FIELD_ROWS = ("field_px", "shear_x_px", "shear_y_px", "invalid_share", "divergence", "curl")


def field_rows(fields: np.ndarray, valid_share: np.ndarray, width_px: int) -> np.ndarray:
    """(F, 6) float32 ``FIELD_ROWS`` of ``fields`` (F, H, W, 3) px (dx, dy, |d|) of frames ``width_px``
    wide and the share of reference markers valid in each frame ``valid_share`` (F,); frames are
    independent. Displacements are rescaled to px of the frame resized to ``FIELD_WIDTH_PX`` wide
    (:func:`fv_algos.real_trials.at_reference_width`), so one grasp filmed at another resolution gives
    the same rows. ValueError naming the grid for fields not on ``FIELD_GRID`` (H, W): the rows' divergence
    and curl are per grid cell."""
    grid_shape = tuple(np.shape(fields)[1:3])
    if grid_shape != FIELD_GRID:
        raise ValueError(f"field grid {'x'.join(map(str, grid_shape))} is not the {FIELD_GRID[0]}x{FIELD_GRID[1]} grid "
                         "the trial models read (their divergence and curl are per grid cell)")
    grid = at_reference_width(fields, width_px)
    ddx_dy, ddx_dx = np.gradient(grid[..., 0], axis=(1, 2))
    ddy_dy, ddy_dx = np.gradient(grid[..., 1], axis=(1, 2))
    return np.stack([grid[..., 2].mean(axis=(1, 2)), grid[..., 0].mean(axis=(1, 2)), grid[..., 1].mean(axis=(1, 2)),
                     1.0 - np.asarray(valid_share, np.float32), (ddx_dx + ddy_dy).mean(axis=(1, 2)),
                     (ddy_dx - ddx_dy).mean(axis=(1, 2))], axis=1).astype(np.float32)


def descriptor_matrix(series: np.ndarray, rows: np.ndarray) -> torch.Tensor:
    """(C, F) float32 ``DESCRIPTORS`` / ``SCALE`` from contact-motion ``series`` (F, 5) and
    :func:`field_rows` ``rows`` (F, 6) of the same frames; ValueError when the counts differ."""
    if rows.shape[0] != series.shape[0]:
        raise ValueError(f"{series.shape[0]} contact-series frames but {rows.shape[0]} fields")
    joined = np.stack([series[:, 0], series[:, 1], series[:, 2], *rows.T,
                       series[:, 3], series[:, 4]]).astype(np.float32)
    return torch.from_numpy(np.nan_to_num(joined / SCALE[:, None], nan=0.0, posinf=0.0, neginf=0.0))


def camera_descriptors(series: np.ndarray, fields: VideoFields) -> torch.Tensor:
    """(C, F) float32 ``DESCRIPTORS`` / ``SCALE`` of one camera: ``series`` (F, 5) from
    :func:`fv_algos.contact_motion.contact_series` and ``fields`` of the same F frames; ValueError
    when the counts differ."""
    return descriptor_matrix(series, field_rows(fields.fields, fields.valid_share, fields.width_px))


TrialInput = list[torch.Tensor]  # one (C, F) descriptor tensor per camera of a trial


def trial_inputs(trials: Sequence[Trial], series: TrialSeries, fields: TrialFields,
                 cameras: Sequence[str] = CAMERAS) -> list[TrialInput]:
    """:func:`camera_descriptors` of every camera of every trial (the cameras it has); ValueError naming
    the cameras with fewer than ``MIN_FRAMES`` frames."""
    require_frames({key: value for key, value in fields.items() if key in series}, MIN_FRAMES)
    return [[camera_descriptors(series[(t.name, c)], fields[(t.name, c)]) for c in cameras if (t.name, c) in series]
            for t in trials]


MAX_LAYERS = 12  # a frame's features then see 8,190 frames on each side (5.5 min at 25 fps)
BALANCES = ("setup", "label")  # how training batches are drawn (TrialNetConfig.balance)


@dataclass(frozen=True)
class TrialNetConfig:
    """hidden: channels of the temporal convolutions; layers: their number (dilations 1, 2, 4, ...:
    a frame's features see 2 * (2**layers - 1) frames on each side); members: networks in the
    ensemble (each with its own weights and loss; the same batches). steps: optimizer steps of
    ``batch`` trials (half slip, half no slip). balance: "setup", each half drawn alike from every set-up
    that has trials of its label (:mod:`fv_algos.setups`; the set-ups given to :func:`fit_trial_net`), or
    "label", from all the trials of its label. lr, weight_decay: AdamW. gain: range of the random factor every
    training trial's descriptors are multiplied by (with random left-right / up-down mirroring).
    stretch: every training trial is resampled in time by a factor drawn log-uniformly from
    [1 / stretch, stretch] (the same motion, slower or faster; 1: never). clip: each descriptor is
    clamped to its [clip, 1 - clip] quantiles over the training trials' frames (0: their min and max).
    held_prefix: probability that a no-slip training trial is cut to its first k frames (both
    cameras, k uniform in [min(MIN_FRAMES, F), F]): a held grasp is held from its start,
    so the running P(slip) of a grasp in progress (:mod:`fv_algos.grasp_judge`) learns that a short
    still grasp is not a slip (0: never). start_swap: probability that a training camera's first
    ``START_FRAMES`` frames are replaced by those of a random training camera of the other label:
    camera start-up bursts (a pressed imprint for a few frames, then gone) are common in some set-ups
    that hold mostly slips, and the trade teaches that a start says nothing of the label (0: never).
    reference_frame: the frame of every video taken as the
    skin at rest, where the descriptors start (frame 0 of the GelSight Mini videos is often stale);
    saved with the model, so that `fv eval` judges the same frames. fps: the frame rate (Hz) the
    descriptors were taken at (:mod:`fv_algos.frame_rate`: a faster camera's frames are picked at it)."""

    hidden: int = 16
    layers: int = 4
    members: int = 5
    steps: int = 1600
    batch: int = 8
    balance: str = "setup"
    lr: float = 3e-3
    weight_decay: float = 1e-2
    gain: tuple[float, float] = (0.8, 1.2)
    stretch: float = 1.4
    clip: float = 0.0
    held_prefix: float = 0.0
    start_swap: float = 0.0
    reference_frame: int = 1
    fps: float = 25.0
    seed: int = 0

    def __post_init__(self) -> None:
        rules = {  # each rule broken is named with its value (not the whole config)
            f"hidden, members and steps >= 1 (got {self.hidden}, {self.members}, {self.steps})":
                min(self.hidden, self.members, self.steps) >= 1,
            f"1 <= layers <= {MAX_LAYERS} (got {self.layers}; 2**layers frames of context)": 1 <= self.layers <= MAX_LAYERS,
            f"an even batch >= 2 (got {self.batch})": self.batch >= 2 and self.batch % 2 == 0,
            f"balance one of {', '.join(BALANCES)} (got {self.balance!r})": self.balance in BALANCES,
            f"0 < gain[0] <= gain[1] (got {self.gain})": 0 < self.gain[0] <= self.gain[1],
            f"stretch >= 1 (got {self.stretch})": self.stretch >= 1,
            f"0 <= clip < 0.5 (got {self.clip})": 0 <= self.clip < 0.5,
            f"0 <= held_prefix <= 1 (got {self.held_prefix})": 0 <= self.held_prefix <= 1,
            f"0 <= start_swap <= 1 (got {self.start_swap})": 0 <= self.start_swap <= 1,
            f"reference_frame >= 0 (got {self.reference_frame})": self.reference_frame >= 0,
            f"a finite fps > 0 (got {self.fps})": 0 < self.fps < float("inf"),
            f"0 < lr < {MAX_LR:.3g} (got {self.lr}; AdamW's first step, 10 lr, is a float32)": 0 < self.lr < MAX_LR,
        }
        broken = [rule for rule, ok in rules.items() if not ok]
        if broken:
            raise ValueError("trial network: " + "; ".join(broken))


class TrialNet(nn.Module):
    """Cameras of one trial -> slip logit, the mean of ``members`` independent networks' logits. The
    descriptors are first clamped to [``low``, ``high``] (C,) (buffers, saved with the weights;
    unbounded until :meth:`set_range`). A member: per camera ``layers`` 1-D convolutions (kernel 5,
    dilation 1, 2, 4, ...) with ReLU over the (C, F) descriptors, then mean and max over the F
    frames (2 * hidden); mean over the cameras; linear. The members are run as one network: member m
    owns channels m * hidden to (m + 1) * hidden of every convolution (grouped after the first) and
    row m of the head, which reads only those channels' pooled features."""

    def __init__(self, hidden: int = 16, layers: int = 4, members: int = 1) -> None:
        super().__init__()
        self.hidden, self.layers, self.members = hidden, layers, members
        width = self.width
        convs: list[nn.Module] = []
        for k in range(layers):
            dilation = 2 ** k  # kernel 5: 2 * dilation frames on each side, kept by as much padding
            convs += [nn.Conv1d(len(DESCRIPTORS) if k == 0 else width, width, 5, padding=2 * dilation,
                                dilation=dilation, groups=1 if k == 0 else members), nn.ReLU()]
        self.temporal = nn.Sequential(*convs)
        self.head = nn.Linear(2 * hidden, members)  # row m: member m's (mean, max) -> its logit
        self.register_buffer("low", torch.full((len(DESCRIPTORS),), -torch.inf))
        self.register_buffer("high", torch.full((len(DESCRIPTORS),), torch.inf))

    def set_range(self, low: torch.Tensor, high: torch.Tensor) -> None:
        """Clamp the descriptors to [``low``, ``high``] (C,) from now on."""
        self.low.copy_(low)
        self.high.copy_(high)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """(N, width, F) temporal features of descriptors ``x`` (N, C, F), clamped first."""
        return self.temporal(torch.clamp(x, self.low[:, None], self.high[:, None]))

    @property
    def width(self) -> int:
        """Channels of the temporal features, all members together."""
        return self.members * self.hidden

    def member_logits(self, pooled: torch.Tensor) -> torch.Tensor:
        """(members,) logits from ``pooled`` (2 * width,): the mean over the frames of every channel,
        then the maximum."""
        own = pooled.view(2, self.members, self.hidden).transpose(0, 1).reshape(self.members, 2 * self.hidden)
        return (self.head.weight * own).sum(dim=1) + self.head.bias

    def logit(self, pooled: torch.Tensor) -> torch.Tensor:
        """Scalar slip logit from ``pooled`` (as :meth:`member_logits`): the members' mean."""
        return self.member_logits(pooled).mean()

    def pooled(self, cameras: TrialInput) -> torch.Tensor:
        """(2 * width,) mean and max over the frames of every channel, averaged over the
        cameras (their (C, F) tensors, any F >= 1)."""
        per_camera = []
        for x in cameras:
            h = self.features(x[None])[0]
            per_camera.append(torch.cat([h.mean(dim=1), h.amax(dim=1)]))
        return torch.stack(per_camera).mean(dim=0)

    @property
    def radius(self) -> int:
        """Frames on each side of a frame that its temporal features depend on (30 for 4 layers)."""
        return sum(c.dilation[0] * (c.kernel_size[0] - 1) // 2 for c in self.temporal if isinstance(c, nn.Conv1d))

    def forward(self, cameras: TrialInput) -> torch.Tensor:
        """Scalar slip logit of one trial (its cameras' (C, F) tensors, any F >= 1): the members' mean."""
        return self.logit(self.pooled(cameras))


class RunningTrial:
    """P(slip) of one camera's grasp so far, from its descriptor columns pushed one frame at a time:
    after every frame exactly what ``net`` says of the camera's descriptors cut at that frame (same
    features, same pooling), at a cost that does not grow with the grasp's length. A frame's features
    depend on ``net.radius`` frames on each side, so a frame more than ``radius`` frames old is final
    and only enters a running sum and maximum; each :meth:`push` recomputes the features of the
    newest frames from the last 2 * radius + 1 columns. ``net`` is put in eval mode."""

    def __init__(self, net: TrialNet) -> None:
        self.net = net.eval()
        self.reset()

    def reset(self) -> None:
        """Forget the grasp: the next :meth:`push` is its first frame."""
        self.frames = 0
        self._columns: collections.deque = collections.deque(maxlen=2 * self.net.radius + 1)  # (C,) each
        self._final = 0  # frames whose features are final
        self._sum = torch.zeros(self.net.width)  # (width,) sum of the final frames' features
        self._max = torch.full((self.net.width,), -torch.inf)  # (width,) their maximum

    @torch.no_grad()
    def push(self, column: torch.Tensor) -> float:
        """P(slip) of the grasp up to and including the frame of ``column`` (C,) (its descriptors,
        as a column of :func:`descriptor_matrix`), in float64 from the float32 logit, so that
        :func:`fv_algos.camera_vote.camera_vote` can take the logit back from it."""
        self._columns.append(column)
        self.frames += 1
        h = self.net.features(torch.stack(tuple(self._columns), dim=1)[None])[0]  # (width, columns)
        first_column = self.frames - h.shape[1]  # column j is frame first_column + j
        newly_final = self.frames - self.net.radius  # frames [self._final, newly_final) become final
        for frame in range(self._final, max(self._final, newly_final)):
            self._sum += h[:, frame - first_column]
            self._max = torch.maximum(self._max, h[:, frame - first_column])
        self._final = max(self._final, newly_final)
        live = h[:, self._final - first_column:]  # never empty: the newest frame is never final
        peak = torch.maximum(self._max, live.amax(dim=1))
        pooled = torch.cat([(self._sum + live.sum(dim=1)) / self.frames, peak])
        return float(expit(self.net.logit(pooled).item()))  # float64: P keeps the logit to |logit| ~ 36


def running_probability(net: TrialNet, x: torch.Tensor) -> np.ndarray:
    """(F,) float64 P(slip) of one camera's (C, F) descriptors cut at every frame: entry t is what
    the pipeline's slip detector publishes after frame t (frame 0: the reference)."""
    running = RunningTrial(net)
    return np.array([running.push(x[:, t]) for t in range(x.shape[1])])


def _running_of(net: TrialNet, inputs: Sequence[TrialInput]) -> list[list[np.ndarray]]:
    """:func:`running_probability` of every camera of every trial in ``inputs``."""
    return [[running_probability(net, x) for x in cameras] for cameras in inputs]


def running_probabilities(net: TrialNet, inputs: Sequence[TrialInput], workers: int = 1) -> list[list[np.ndarray]]:
    """Per trial, per camera: :func:`running_probability` (F,), the trials split into ``workers``
    contiguous parts run in spawned processes of one torch thread each (1: in this process;
    :func:`fv_algos.trial_eval.map_folds`)."""
    parts = [[inputs[i] for i in part] for part in np.array_split(np.arange(len(inputs)), workers)]
    return [cameras for part in map_folds(partial(_running_of, net), parts, workers) for cameras in part]


def stretch_in_time(x: torch.Tensor, factor: float) -> torch.Tensor:
    """``x`` (C, F) descriptors resampled (linearly) to max(2, round(F * factor)) frames spanning
    the same trial, the ``PER_FRAME`` rates divided by ``factor``: the same motion ``factor`` times
    slower."""
    frames = x.shape[1]
    at = np.linspace(0.0, frames - 1, max(2, round(frames * factor)))
    left = np.floor(at).astype(np.int64)
    right = np.minimum(left + 1, frames - 1)
    weight = torch.from_numpy((at - left).astype(np.float32))
    scale = torch.from_numpy(np.where(PER_FRAME, 1.0 / factor, 1.0).astype(np.float32))[:, None]
    return (x[:, left] * (1.0 - weight) + x[:, right] * weight) * scale


def _augment(x: torch.Tensor, rng: np.random.Generator, config: TrialNetConfig) -> torch.Tensor:
    """``x`` (C, F) times a random gain, randomly mirrored left-right and up-down, stretched in time
    by a random factor (``config.gain``, ``config.stretch``)."""
    sign = np.ones(len(DESCRIPTORS), np.float32)
    for mirror in (MIRROR_X, MIRROR_Y):
        if rng.random() < 0.5:
            sign = sign * mirror
    x = x * torch.from_numpy(sign * np.float32(rng.uniform(*config.gain)))[:, None]
    if config.stretch == 1:
        return x
    log_stretch = np.log(config.stretch)
    return stretch_in_time(x, float(np.exp(rng.uniform(-log_stretch, log_stretch))))


def _drawn(rng: np.random.Generator, probability: float) -> bool:
    """True with ``probability``; no random draw when it is 0, so an option left off does not move the
    training's random stream."""
    return probability != 0 and rng.random() < probability


def _held_prefix(cameras: TrialInput, rng: np.random.Generator, probability: float) -> TrialInput:
    """With ``probability`` (:func:`_drawn`), the cameras' (C, F) descriptors cut to their first k frames,
    k uniform in [min(MIN_FRAMES, F), F] (F: the shortest camera's frames); otherwise ``cameras`` as they
    are."""
    if not _drawn(rng, probability):
        return cameras
    frames = min(x.shape[1] for x in cameras)
    keep = int(rng.integers(min(MIN_FRAMES, frames), frames + 1))
    return [x[:, :keep] for x in cameras]


def _start_swap(x: torch.Tensor, donors: Sequence[TrialInput], rng: np.random.Generator,
                probability: float) -> torch.Tensor:
    """With ``probability`` (:func:`_drawn`), the camera's (C, F) descriptors with their first
    ``START_FRAMES`` frames replaced by those of a random camera of a random trial of ``donors``; otherwise
    ``x`` as it is. A camera of at most ``START_FRAMES`` frames, or a donor of as few, is kept as it is."""
    if not _drawn(rng, probability):
        return x
    cameras = donors[int(rng.integers(len(donors)))]
    donor = cameras[int(rng.integers(len(cameras)))]
    if min(x.shape[1], donor.shape[1]) <= START_FRAMES:
        return x
    return torch.cat([donor[:, :START_FRAMES], x[:, START_FRAMES:]], dim=1)


@contextmanager
def _without_onednn() -> Iterator[None]:
    """PyTorch's own convolutions inside: oneDNN builds a kernel for every new input length, and a
    time-stretched trial brings a new length almost every call (training runs 3 to 4 times faster)."""
    enabled = torch.backends.mkldnn.enabled
    torch.backends.mkldnn.enabled = False
    try:
        yield
    finally:
        torch.backends.mkldnn.enabled = enabled


def _check_setups(setups: Sequence[str] | None, trials: int) -> None:
    """ValueError unless ``setups`` (None: not given) names one set-up per trial."""
    if setups is not None and len(setups) != trials:
        raise ValueError(f"{len(setups)} set-ups given for {trials} trials")


def _label_cells(labels: np.ndarray, setups: Sequence[str] | None) -> list[list[np.ndarray]]:
    """Per label (slip, then no slip), the trial indices of each set-up that has trials of it (set-ups sorted;
    None: one set-up)."""
    names = np.zeros(len(labels), int) if setups is None else np.asarray(setups)
    cells = [[np.flatnonzero((labels == label) & (names == name)) for name in np.unique(names)] for label in (1, 0)]
    return [[cell for cell in label_cells if cell.size] for label_cells in cells]


def _balanced_picks(cells: list[list[np.ndarray]], batch: int, rng: np.random.Generator) -> np.ndarray:
    """(batch,) trial indices: half from each label's ``cells``, spread alike over them (the remainder to cells
    drawn at random); with one cell per label, ``batch`` / 2 of each label drawn from all its trials."""
    picks = []
    for label_cells in cells:
        counts = np.full(len(label_cells), batch // 2 // len(label_cells))
        if batch // 2 % len(label_cells):
            counts[rng.permutation(len(label_cells))[:batch // 2 % len(label_cells)]] += 1
        picks += [rng.choice(cell, n) for cell, n in zip(label_cells, counts)]
    return np.concatenate(picks)


def fit_trial_net(inputs: Sequence[TrialInput], labels: np.ndarray,
                  config: TrialNetConfig = TrialNetConfig(), init: TrialNet | None = None,
                  setups: Sequence[str] | None = None) -> TrialNet:
    """Train a :class:`TrialNet` on ``inputs`` with ``labels`` (M,) 0/1 (both classes needed):
    AdamW on every member's binary cross-entropy of balanced batches of augmented trials (``config.balance``
    "setup": over the set-ups ``setups`` (M,) names, None: one set-up). ``init``: a network to fine-tune (its
    weights are the start; ``config`` must give its hidden, layers and members), its descriptors' clamp range
    set anew from ``inputs`` as for a new network."""
    labels = np.asarray(labels)
    slip, still = np.flatnonzero(labels == 1), np.flatnonzero(labels == 0)
    if slip.size == 0 or still.size == 0:
        raise ValueError(f"training needs slip and no-slip trials, got {slip.size} and {still.size}")
    _check_setups(setups, len(labels))
    cells = _label_cells(labels, setups if config.balance == "setup" else None)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    net = TrialNet(config.hidden, config.layers, config.members)
    if init is not None:
        if (init.hidden, init.layers, init.members) != (config.hidden, config.layers, config.members):
            raise ValueError(f"the network to fine-tune has hidden {init.hidden}, layers {init.layers}, members "
                             f"{init.members}; the training asks for {config.hidden}, {config.layers}, "
                             f"{config.members}")
        net.load_state_dict(init.state_dict())
    frames = torch.cat([x for cameras in inputs for x in cameras], dim=1).numpy()  # (C, all frames)
    low, high = (torch.from_numpy(np.quantile(frames, q, axis=1).astype(np.float32))
                 for q in (config.clip, 1 - config.clip))
    net.set_range(low, high)
    optimizer = torch.optim.AdamW(net.parameters(), config.lr, weight_decay=config.weight_decay)
    loss_fn = nn.BCEWithLogitsLoss()
    donors = [[inputs[i] for i in still], [inputs[i] for i in slip]]  # by label: the other label's starts
    with _without_onednn():
        for _ in range(config.steps):
            picks = _balanced_picks(cells, config.batch, rng)
            cut = [_held_prefix(inputs[i], rng, config.held_prefix) if labels[i] == 0 else inputs[i] for i in picks]
            swapped = [[_start_swap(x, donors[1 - labels[i]], rng, config.start_swap) for x in cameras]
                       for i, cameras in zip(picks, cut)]
            logits = torch.stack([net.member_logits(net.pooled([_augment(x, rng, config) for x in cameras]))
                                  for cameras in swapped])  # (batch, members)
            target = torch.as_tensor(labels[picks], dtype=torch.float32)[:, None].expand_as(logits)
            loss = loss_fn(logits, target)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    return net.eval()


@torch.no_grad()
def trial_probability(net: TrialNet, inputs: Sequence[TrialInput]) -> np.ndarray:
    """(M,) slip probability of each trial."""
    return np.array([torch.sigmoid(net(x)).item() for x in inputs])


def save_trial_model(path: str | Path, net: TrialNet, config: TrialNetConfig,
                     params: ContactMotionParams = ContactMotionParams()) -> Path:
    """Write ``net`` (+ its training config, the descriptors and the contact-motion parameters);
    ValueError when ``config`` gives another hidden, layers or members than ``net`` has."""
    if (net.hidden, net.layers, net.members) != (config.hidden, config.layers, config.members):
        raise ValueError(f"network of hidden {net.hidden}, layers {net.layers}, members {net.members} "
                         f"saved with {config}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"kind": KIND, "descriptors": list(DESCRIPTORS), "scale": SCALE.tolist(), "config": asdict(config),
                "params": asdict(params), "state_dict": net.state_dict()}, path)
    return path


def _read(path: str | Path) -> dict | None:
    """The payload of ``path`` when it holds a model written by :func:`save_trial_model` (tensors and
    plain values only: read with ``weights_only``), else None."""
    try:
        data = read_torch_file(Path(path))
    except ValueError:
        return None
    return data if isinstance(data, dict) and data.get("kind") == KIND else None


class TrialModel(NamedTuple):
    """A trial-level model file: the network, its contact-motion parameters, the frame of each
    video it takes as the reference, the frame rate (Hz) it judges at and the time stretch it was
    trained with (`TrialNetConfig.reference_frame`, `fps`, `stretch`)."""

    net: TrialNet
    params: ContactMotionParams
    reference_frame: int
    fps: float
    stretch: float


def read_trial_model(path: str | Path) -> TrialModel | None:
    """The :class:`TrialModel` of a file written by :func:`save_trial_model`, or None when ``path``
    holds another kind of file (one read either way); ValueError when it was written for other
    descriptors. Files written before layers / members / reference_frame / fps / stretch: 3 layers, 1
    member, frame 1, 25 fps (the GelSight Mini videos they were trained on), no stretch."""
    data = _read(path)
    if data is None:
        return None
    if data["descriptors"] != list(DESCRIPTORS) or data["scale"] != SCALE.tolist():
        raise ValueError(f"{path}: descriptors {data['descriptors']} (scale {data['scale']}) differ from this "
                         f"code's {list(DESCRIPTORS)} ({SCALE.tolist()}): retrain the model with `fv real train`")
    config = data["config"]
    net = TrialNet(int(config["hidden"]), int(config.get("layers", 3)), int(config.get("members", 1)))
    net.load_state_dict(data["state_dict"])
    params = data["params"]
    return TrialModel(net.eval(), ContactMotionParams(**{**params, "size_px": tuple(params["size_px"])}),
                      int(config.get("reference_frame", 1)), float(config.get("fps", 25.0)),
                      float(config.get("stretch", 1.0)))


def load_trial_model(path: str | Path) -> TrialModel:
    """:func:`read_trial_model`, with a ValueError when ``path`` holds another kind of file."""
    model = read_trial_model(path)
    if model is None:
        raise ValueError(f"{path} is not a trial-level slip model (its kind is not {KIND!r}: a window model, or no "
                         "model)")
    return model


def judge_trials(probability: np.ndarray, labels: np.ndarray) -> dict[str, object]:
    """Trial accuracy, F1, confusion ([[TN, FP], [FN, TP]]), n_trials and the probabilities (M,) of
    trials with ``labels`` (M,) (slip when p >= 0.5)."""
    m = classification_metrics(labels, (np.asarray(probability) >= 0.5).astype(np.int64))
    return {"trial_accuracy": m.accuracy, "trial_f1": m.f1, "confusion": [list(r) for r in m.confusion],
            "n_trials": m.n, "probability": np.asarray(probability).tolist()}


def _held_out(inputs: Sequence[TrialInput], labels: np.ndarray, config: TrialNetConfig, online: bool,
              init: TrialNet | None, setups: Sequence[str] | None,
              test: np.ndarray) -> tuple[np.ndarray, list[list[np.ndarray]] | None]:
    """Slip probability (T,) of the ``test`` trials (mask (M,)) from a network trained on the others (fine-tuned
    from ``init`` when given; batches balanced over their ``setups``), and when ``online`` each test trial's
    per-camera :func:`running_probability` (else None)."""
    train = np.flatnonzero(~test)
    net = fit_trial_net([inputs[i] for i in train], labels[~test], config, init,
                        None if setups is None else [setups[i] for i in train])
    tested = [inputs[i] for i in np.flatnonzero(test)]
    running = running_probabilities(net, tested) if online else None
    return trial_probability(net, tested), running


def cross_validate_trials(inputs: Sequence[TrialInput], labels: np.ndarray, objects: Sequence[str], folds: int,
                          seed: int = 0, config: TrialNetConfig = TrialNetConfig(), workers: int = 1,
                          progress: bool = False, online: bool = False,
                          init: TrialNet | None = None, setups: Sequence[str] | None = None) -> dict[str, object]:
    """Object-held-out cross-validation of :class:`TrialNet`: ``folds`` object groups (dealt with
    ``seed``; ``folds`` = number of objects leaves one object out), a network trained per fold on
    the other objects' trials, the folds in ``workers`` spawned processes of one torch thread each
    (1: in this process; the same figures either way; :func:`map_folds`), with a progress bar
    over the folds when ``progress``. Returns {"folds": per fold objects, trials,
    trial accuracy, confusion; "summary": mean, std, min, worst fold, pooled accuracy and confusion}
    and, when ``online``, "running": per trial (in the order of ``inputs``), per camera, the held-out
    network's P(slip) after every frame as a list (:func:`running_probability`). ``init``: every fold's network is
    fine-tuned from it; ``setups``: each trial's set-up, over which training batches are balanced
    (:func:`fit_trial_net`)."""
    names, labels = np.asarray(objects), np.asarray(labels)
    _check_setups(setups, len(inputs))
    groups = object_folds(objects, folds, seed)
    tests = [np.isin(names, group) for group in groups]
    results = map_folds(partial(_held_out, inputs, labels, config, online, init, setups), tests, workers, progress)
    rows = [{"fold": k, "objects": group, "trials": np.flatnonzero(test).tolist(),
             **judge_trials(probability, labels[test])}
            for k, (group, test, (probability, _)) in enumerate(zip(groups, tests, results))]
    report: dict[str, object] = {"folds": rows, "summary": fold_summary(rows)}
    if online:
        running: list[list[list[float]]] = [[] for _ in inputs]
        for test, (_, fold_running) in zip(tests, results):
            for i, cameras in zip(np.flatnonzero(test), fold_running):
                running[i] = [series.tolist() for series in cameras]
        report["running"] = running
    return report
