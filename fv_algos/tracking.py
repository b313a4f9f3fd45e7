"""Marker tracking: the paper's nearest-neighbour tracker and a robust one-to-one tracker.

Markers are a fixed set of N reference positions (no grid assumption). Each frame the
tracker matches them to the frame's detections and returns a `TrackState`. Coordinates
are (x, y) px.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from fv_algos.detection import Detections
from fv_algos.reference_markers import checked_reference, point_rows


# Rejecting an implausible match changes its neighbours' medians, so the check is repeated.
_PLAUSIBILITY_PASSES = 3
# Candidate detections per marker in a gated round (a free one within the gate is almost
# always among them) and in the global fallback (a disc of 2 pitches holds ~13 markers).
_ROUND_CANDIDATES = 4
_TRANSPORT_CANDIDATES = 16


@dataclass(frozen=True)
class TrackerParams:
    """Tracker settings; distances are fractions of the median reference marker spacing.

    method: 'nearest' (the paper: each marker takes its nearest detection within the gate,
        two markers may take one detection, a missed marker keeps its last position) or
        'assignment' (one-to-one, neighbour-predicted, plausibility-checked).
    gate_ratio: the paper's distance threshold d, and the final gate of 'assignment'.
    strict_gate_ratio: gate of the neighbour-propagation rounds of 'assignment'.
    rounds: at most this many propagation rounds per frame.
    neighbours: number of reference neighbours used for prediction and plausibility.
    tolerance_ratio: plausibility floor of `neighbour_consistency`.
    area_ratio_max: a detection whose area differs from the marker's reference area by
        more than this factor (either way) is rejected; 0 disables the check.
    use_velocity: predict markers seen in the last two frames with their last step.
    transport_ratio: radius of the two fallbacks of 'assignment' for markers that the
        neighbour-grown match leaves unmatched next to spare detections: the global
        one-to-one matching (it needs no velocity and handles steps of up to about this
        many pitches) and the local re-acquisition of a few lost markers; 0 disables both.
    transport_edge_share: the global fallback runs only when at least this share of an
        array edge (sqrt(N) of N markers), and at least 2, of both markers and detections
        are left unmatched (a lattice matched one pitch off leaves a whole edge row so);
        fewer go to the local re-acquisition, which costs far less.
    rest_ratio: radius of the return to rest and of the wrong-match check of 'assignment'
        (`Tracker._wrong_matches`). Return to rest: when all markers but fewer
        than the global fallback's trigger have a detection this close to their reference
        position, the skin is back at rest; a match that claims a marker moved more than
        ``gate_ratio`` or left one unpaired is then wrong (e.g. locked one pitch off by a
        jump the velocity could not follow): the markers take those detections and the
        velocity restarts from 0. A deformed skin cannot put nearly every marker on a
        reference position (a whole lattice shifted by one pitch leaves an edge row
        without one); 0 disables both.
    swap_lost_share: the wrong-match check runs only while at least this share of the markers
        is unmatched. A transparent skin's reference holds background clutter that is lost once
        the scene behind it changes, leaving markers without the reference neighbours that
        `neighbour_consistency` judges them by and keeping the skin from counting as back at
        rest. With nearly all markers matched (an opaque skin, e.g. a GelSight Mini) those two
        judge every marker; there the check would change fields that trained models depend on
        (it acted on 7 of the 300 videos of the incipient-slip dataset, with at most 10.4% of
        the markers unmatched; with 0.15 it acts on none).
    """

    method: Literal["nearest", "assignment"] = "assignment"
    gate_ratio: float = 0.5
    strict_gate_ratio: float = 0.35
    rounds: int = 6
    neighbours: int = 6
    tolerance_ratio: float = 0.25
    area_ratio_max: float = 3.0
    use_velocity: bool = True
    transport_ratio: float = 2.0
    transport_edge_share: float = 0.25
    rest_ratio: float = 0.15
    swap_lost_share: float = 0.15

    def __post_init__(self) -> None:
        if self.method not in ("nearest", "assignment"):
            raise ValueError(f"TrackerParams.method must be 'nearest' or 'assignment', got {self.method!r}")
        if not 0.0 < self.strict_gate_ratio <= self.gate_ratio:
            raise ValueError(
                f"need 0 < strict_gate_ratio <= gate_ratio, got {self.strict_gate_ratio}, {self.gate_ratio}"
            )
        if self.rounds < 1 or self.neighbours < 1:
            raise ValueError(f"rounds and neighbours must be >= 1, got {self.rounds}, {self.neighbours}")
        if not self.tolerance_ratio > 0.0:
            raise ValueError(f"tolerance_ratio must be > 0, got {self.tolerance_ratio}")
        if self.transport_ratio < 0.0:
            raise ValueError(f"transport_ratio must be >= 0, got {self.transport_ratio}")
        if not 0.0 <= self.rest_ratio < 0.5:
            raise ValueError(f"rest_ratio must be in [0, 0.5), got {self.rest_ratio}")
        if not 0.0 <= self.swap_lost_share <= 1.0:
            raise ValueError(f"swap_lost_share must be in [0, 1], got {self.swap_lost_share}")
        if not 0.0 <= self.transport_edge_share <= 1.0:
            raise ValueError(f"transport_edge_share must be in [0, 1], got {self.transport_edge_share}")
        if self.area_ratio_max != 0.0 and not self.area_ratio_max > 1.0:
            raise ValueError(f"area_ratio_max must be 0 (off) or > 1, got {self.area_ratio_max}")


@dataclass(frozen=True)
class TrackState:
    """Tracked markers after one frame.

    reference_px: (N, 2) float64 undeformed positions. current_px: (N, 2) float64 positions
    (the last measured one for a marker not seen this frame). valid: (N,) bool, measured and
    plausible this frame. frames_since_seen: (N,) int64, 0 when valid. swapped: (N,) bool,
    markers whose match this frame was a detected identity swap (`Tracker._wrong_matches`),
    dropped and so not valid.
    """

    reference_px: np.ndarray
    current_px: np.ndarray
    valid: np.ndarray
    frames_since_seen: np.ndarray
    swapped: np.ndarray

    @property
    def displacement_px(self) -> np.ndarray:
        """(N, 2) float64 current minus reference position, px."""
        return self.current_px - self.reference_px


def neighbour_graph(reference_px: np.ndarray, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """k nearest reference neighbours of each marker.

    reference_px: (N, 2) float64 finite px. Returns indices (N, k) int64 (k = min(neighbours,
    N - 1); a marker with no other marker gets an empty row) and spacing (N,) float64 px,
    the distance to the nearest other marker (the median spacing when N == 1).
    """
    n = reference_px.shape[0]
    k = min(neighbours, n - 1)
    if k <= 0:
        return np.zeros((n, 0), dtype=np.int64), np.ones(n)
    distances, indices = cKDTree(reference_px).query(reference_px, k=k + 1)
    spacing = np.maximum(distances[:, 1], 1e-9)
    return indices[:, 1:].astype(np.int64), spacing


def _gather_rows(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """values (N, ...) taken at the rows `index` (P, k) int: (P, k, ...), as values[index]
    (numpy's take, several times faster than fancy indexing for (N, 2) rows)."""
    return values.take(index, axis=0)


def masked_median(values: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median over axis 1 of `values` (N, k, C) where `mask` (N, k) is True.

    Returns medians (N, C) float64 (0 where a row has no True entry) and has (N,) bool.
    """
    n, k, c = values.shape
    if k == 0:
        return np.zeros((n, c)), np.zeros(n, dtype=bool)
    if mask.all():
        ordered = np.sort(values, axis=1)
        return 0.5 * (ordered[:, (k - 1) // 2] + ordered[:, k // 2]), np.ones(n, dtype=bool)
    filled = np.where(mask[:, :, None], values, np.inf)
    ordered = np.sort(filled, axis=1)
    count = mask.sum(axis=1)
    rows = np.arange(n)  # the middle of count <= k values: both indices are < k
    low = ordered[rows, np.maximum(count - 1, 0) >> 1]
    high = ordered[rows, count >> 1]
    has = count > 0
    median = np.where(has[:, None], 0.5 * (low + high), 0.0)
    return median, has


def _outside_band(
    displacement: np.ndarray, nb_disp: np.ndarray, nb_valid: np.ndarray, spacing: np.ndarray, tolerance_ratio: float
) -> np.ndarray:
    """(P,) bool: markers whose displacement (P, 2) px leaves the band of their valid neighbours'
    displacements nb_disp (P, k, 2) px (nb_valid (P, k) bool).

    The band is the neighbours' median displacement +/- (tolerance_ratio * spacing (P,) px + 3 x
    the neighbours' median absolute deviation). Markers with fewer than 2 valid neighbours are
    not judged (False).
    """
    median, _ = masked_median(nb_disp, nb_valid)
    offset = nb_disp - median[:, None, :]
    deviation = np.hypot(offset[:, :, 0], offset[:, :, 1])
    mad, _ = masked_median(deviation[:, :, None], nb_valid)
    tolerance = tolerance_ratio * spacing + 3.0 * mad[:, 0]
    residual = np.hypot(*(displacement - median).T)
    judged = nb_valid.shape[1] >= 2 if nb_valid.all() else nb_valid.sum(axis=1) >= 2
    return judged & (residual > tolerance)


def _inconsistent(
    displacement: np.ndarray, valid: np.ndarray, graph: np.ndarray, spacing: np.ndarray, tolerance_ratio: float
) -> np.ndarray:
    """(N,) bool: valid markers whose displacement (N, 2) px leaves the band (`_outside_band`) of
    their valid reference neighbours `graph` (N, k); spacing (N,) px."""
    if graph.shape[1] == 0:
        return np.zeros(displacement.shape[0], dtype=bool)
    return valid & _outside_band(displacement, _gather_rows(displacement, graph), valid[graph], spacing,
                                 tolerance_ratio)


def neighbour_consistency(
    reference_px: np.ndarray,
    current_px: np.ndarray,
    valid: np.ndarray,
    neighbours: int = 6,
    tolerance_ratio: float = 0.25,
) -> np.ndarray:
    """Flag markers whose displacement disagrees with their neighbours' (swap / wrong match test).

    reference_px, current_px: (N, 2) float64 px; valid: (N,) bool. Neighbours are the
    `neighbours` nearest markers in the reference. A valid marker is flagged when its
    displacement is farther from its valid neighbours' median displacement than
    tolerance_ratio x its spacing + 3 x the neighbours' median absolute deviation (a smooth
    field passes, a swapped or wrongly matched marker, off by ~one pitch, does not).
    Returns (N,) bool, True = inconsistent. Non-finite rows count as not valid.
    """
    ref = point_rows(reference_px, "reference_px")
    cur = point_rows(current_px, "current_px")
    mask = np.asarray(valid, dtype=bool)
    if cur.shape != ref.shape or mask.shape != (ref.shape[0],):
        raise ValueError(f"shapes disagree: reference {ref.shape}, current {cur.shape}, valid {mask.shape}")
    finite_ref = np.all(np.isfinite(ref), axis=1)
    if not finite_ref.all():
        raise ValueError("reference_px holds non-finite coordinates")
    mask = mask & np.all(np.isfinite(cur), axis=1)
    graph, spacing = neighbour_graph(ref, neighbours)
    displacement = np.where(mask[:, None], cur - ref, 0.0)
    return _inconsistent(displacement, mask, graph, spacing, tolerance_ratio)


def _transport(pred: np.ndarray, det: np.ndarray, radius: float) -> np.ndarray:
    """Global one-to-one matching: the most pairs within `radius` px, then the least sum of squares.

    pred: (N, 2) predicted marker positions, det: (M, 2) detections, px. Among the
    assignments pairing as many markers as possible with detections less than `radius`
    away (each marker's `_TRANSPORT_CANDIDATES` nearest), the one with the smallest sum of
    squared distances (scipy.optimize.linear_sum_assignment) is returned as (N,) int64
    detection indices, -1 = unpaired. Unlike a nearest-neighbour or gated match this sees
    the whole marker array at once: shifting a
    lattice by one pitch leaves a row of markers and one of detections unpaired at its edge,
    so the true motion wins even when it exceeds half a pitch everywhere.
    """
    n, m = pred.shape[0], det.shape[0]
    k = min(_TRANSPORT_CANDIDATES, m)
    dist, idx = cKDTree(det).query(pred, k=k, distance_upper_bound=radius)
    dist, idx = dist.reshape(n, k), idx.reshape(n, k)
    ok = idx < m
    rows = np.broadcast_to(np.arange(n)[:, None], (n, k))[ok]
    # A pair costs at most 1; a missing pair costs more than all real pairs together, so
    # the number of pairs comes first.
    missing = float(n + 1)
    cost = np.full((n, m), missing)
    cost[rows, idx[ok]] = (dist[ok] / radius) ** 2
    r, c = linear_sum_assignment(cost)
    real = cost[r, c] < missing
    out = np.full(n, -1, dtype=np.int64)
    out[r[real]] = c[real]
    return out


class Tracker:
    """Tracks a fixed set of reference markers through frames of detections.

    Usage: `Tracker(reference, params)`, then `step(detections) -> TrackState` per frame;
    `reset(reference)` starts over from new reference detections. `cluttered`: the reference frame
    showed blobs besides the marker lattice (the background behind a transparent skin,
    `fv_algos.detection.drop_crowded_markers`); the global fallback's match is then taken only when it
    matches at least its trigger's count of markers more than the match grown from the velocity
    prediction, not one more: among the background's blobs, winning by one or two, it shifted groups of
    markers by a pitch, which then stayed valid (FingerVision video behind which a QR card passes).
    """

    def __init__(self, reference: Detections, params: TrackerParams = TrackerParams(),
                 cluttered: bool = False) -> None:
        self.params = params
        self.cluttered = cluttered
        self.reset(reference)

    def reset(self, reference: Detections) -> None:
        """Take `reference` (finite centres (N, 2) px, N >= 1, each marker once) as the undeformed
        markers; ValueError for centres `checked_reference` refuses (e.g. a marker listed twice)."""
        ref = checked_reference(reference.centres_px, "reference centres_px")
        areas = np.asarray(reference.areas_px2, dtype=np.float64)
        if areas.shape != (ref.shape[0],):
            raise ValueError(f"reference areas_px2 must have shape ({ref.shape[0]},), got {areas.shape}")
        self._ref = ref
        self._ref_areas = areas
        self._cur = ref.copy()
        self._velocity = np.zeros_like(ref)
        self._valid = np.ones(ref.shape[0], dtype=bool)
        self._since = np.zeros(ref.shape[0], dtype=np.int64)
        self._swapped = np.zeros(ref.shape[0], dtype=bool)
        self._graph, self._spacing = neighbour_graph(ref, self.params.neighbours)
        self._ref_tree = cKDTree(ref)
        self.pitch_px = float(np.median(self._spacing)) if ref.shape[0] > 1 else 1.0
        self._transport_trigger = max(2, int(np.ceil(self.params.transport_edge_share * np.sqrt(ref.shape[0]))))
        self._rest_probe = np.linspace(0, ref.shape[0] - 1, min(ref.shape[0], 2 * self._transport_trigger)).astype(int)

    @property
    def state(self) -> TrackState:
        """The current `TrackState` (copies)."""
        return TrackState(self._ref.copy(), self._cur.copy(), self._valid.copy(), self._since.copy(),
                          self._swapped.copy())

    def step(self, detections: Detections) -> TrackState:
        """Match one frame's detections (rows with non-finite coordinates are ignored)."""
        det = point_rows(detections.centres_px, "detections.centres_px")
        areas = np.asarray(detections.areas_px2, dtype=np.float64).reshape(-1)
        if areas.shape[0] != det.shape[0]:
            raise ValueError(f"detections: {det.shape[0]} centres but {areas.shape[0]} areas")
        if not (np.isfinite(det).all() and np.isfinite(areas).all()):
            finite = np.all(np.isfinite(det), axis=1) & np.isfinite(areas)
            det, areas = det[finite], areas[finite]
        at_rest = False
        if self.params.method == "nearest":
            matched = self._match_nearest(det)
            self._swapped = np.zeros(self._ref.shape[0], dtype=bool)
        else:
            matched = self._match_assignment(det, areas)
            rest = self._rest_match(det, areas, matched)
            at_rest = rest is not None
            matched = matched if rest is None else rest
            self._swapped = self._wrong_matches(det, matched)
            matched = np.where(self._swapped, -1, matched)
        seen = matched >= 0
        new = self._cur.copy()
        new[seen] = det[matched[seen]]
        both = seen & self._valid & (not at_rest)
        self._velocity = np.where(both[:, None], new - self._cur, 0.0)
        self._cur = new
        self._valid = seen
        self._since = np.where(seen, 0, self._since + 1)
        return self.state

    def hold_still(self) -> None:
        """Take the markers as still (zero velocity) in the next step's prediction: after a step whose motion
        spans more than a frame (`Perception.resume`, from the reference to a deformed frame), that motion says
        nothing of the next frame's and, taken as its prediction, it put markers a pitch off."""
        self._velocity = np.zeros_like(self._ref)

    def _rest_match(self, det: np.ndarray, areas: np.ndarray, matched: np.ndarray) -> np.ndarray | None:
        """The return to rest (`TrackerParams.rest_ratio`): (N,) int64 detection index per
        marker (-1 = none), or None when the skin is not at rest or `matched` (N,) agrees
        (checked only when `matched` leaves a marker unpaired or moved beyond the gate).

        At rest each marker takes the detection within the radius of its reference position
        (when it passes the area check); a marker with none keeps its pair in `matched` when no
        other marker took that detection. det: (M, 2) px, areas: (M,) px^2."""
        radius = self.params.rest_ratio * self.pitch_px
        if radius == 0.0 or det.shape[0] == 0:
            return None
        seen = matched >= 0
        if seen.all() and np.all(np.hypot(*(det[matched] - self._ref).T) <= self.params.gate_ratio * self.pitch_px):
            return None
        # A few markers spread over the array first: a deformed skin fails them at once.
        gap = self._ref[self._rest_probe, None, :] - det[None]
        if np.count_nonzero(np.einsum("ijk,ijk->ij", gap, gap).min(axis=1) > radius * radius) >= self._transport_trigger:
            return None
        dist, idx = cKDTree(det).query(self._ref, k=1, distance_upper_bound=radius)
        rows, cols = self._area_checked(np.flatnonzero(np.isfinite(dist)), idx[np.isfinite(dist)], areas)
        if self._ref.shape[0] - rows.size >= self._transport_trigger:
            return None
        taken = np.zeros(det.shape[0], dtype=bool)
        taken[cols] = True
        rest = np.where(seen & ~taken[np.maximum(matched, 0)], matched, -1)
        rest[rows] = cols
        return None if np.array_equal(rest, matched) else rest

    def _wrong_matches(self, det: np.ndarray, matched: np.ndarray) -> np.ndarray:
        """(N,) bool: identity swaps in `matched` (N,) (detection index per marker, -1 = none;
        det: (M, 2) px), checked only while at least `TrackerParams.swap_lost_share` of the markers
        are unmatched.

        A suspect (`_swap_suspects`) is a swap while the detection at its own reference position
        is taken by no marker. Dropping a swap frees its detection, which can make the suspect
        that sits on it a swap in turn: a chain of markers each on its neighbour's dot is undone
        from its free end.
        """
        seen = matched >= 0
        swapped = np.zeros(seen.size, dtype=bool)
        lost = np.count_nonzero(~seen)
        if self.params.rest_ratio == 0.0 or lost == seen.size or lost < self.params.swap_lost_share * seen.size:
            return swapped
        suspects, own_dots = self._swap_suspects(det, matched)
        claimed = np.zeros(det.shape[0], dtype=bool)
        claimed[matched[seen]] = True
        while (drop := ~swapped[suspects] & ~claimed[own_dots]).any():
            swapped[suspects[drop]] = True
            claimed[matched[suspects[drop]]] = False
        return swapped

    def _swap_suspects(self, det: np.ndarray, matched: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Markers (S,) int64 whose match may be a swap, and the detections (S,) int64 at their own
        reference positions; `matched` (N,) detection index per marker (-1 = none), det (M, 2) px.

        A marker matched more than ``gate_ratio`` from its reference position has hopped when it
        sits on another marker's reference position or a detection lies at its own (both within
        the rest radius, `TrackerParams.rest_ratio`). A hopped marker with a detection at its own
        reference position is a suspect when its displacement leaves the band (`_outside_band`)
        of the `neighbours` matched markers nearest in the reference that have not hopped. Unlike
        `neighbour_consistency` this judges a marker whose reference neighbours are lost (behind a
        transparent skin most of them may be background clutter that has since gone) or hopped
        along with it (a chain of markers each on its neighbour's dot agrees with itself).
        """
        radius = self.params.rest_ratio * self.pitch_px
        none = np.zeros(0, dtype=np.int64)
        seen = matched >= 0
        displacement = det[np.maximum(matched, 0)] - self._ref
        far = np.flatnonzero(seen & (np.hypot(*displacement.T) > self.params.gate_ratio * self.pitch_px))
        if far.size == 0:
            return none, none
        hop_gap, _ = self._ref_tree.query(det[matched[far]], distance_upper_bound=radius)
        rest_gap, own_dots = cKDTree(det).query(self._ref[far], distance_upper_bound=radius)
        has_dot = np.isfinite(rest_gap)
        hopped = np.isfinite(hop_gap) | has_dot
        judges = np.setdiff1d(np.flatnonzero(seen), far[hopped])
        if judges.size < 2 or not has_dot.any():
            return none, none
        judged = far[has_dot]
        k = min(self.params.neighbours, judges.size)
        _, nearest = cKDTree(self._ref[judges]).query(self._ref[judged], k=k)
        around = judges[nearest.reshape(-1, k)]
        outside = _outside_band(displacement[judged], _gather_rows(displacement, around),
                                np.ones(around.shape, dtype=bool), self._spacing[judged], self.params.tolerance_ratio)
        return judged[outside], own_dots[has_dot][outside]

    def _match_nearest(self, det: np.ndarray) -> np.ndarray:
        """The paper: nearest detection within the gate, several markers may share one."""
        matched = np.full(self._ref.shape[0], -1, dtype=np.int64)
        if det.shape[0] == 0:
            return matched
        dist, idx = cKDTree(det).query(self._cur, k=1, distance_upper_bound=self.params.gate_ratio * self.pitch_px)
        hit = np.isfinite(dist)
        matched[hit] = idx[hit]
        return matched

    def _neighbour_prediction(
        self, matched: np.ndarray, det: np.ndarray, base: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N, 2) predicted from matched neighbours' motion, and (N,) bool where possible.

        A marker moves from `base` (N, 2) px (`_base_prediction`) by its matched neighbours'
        median step from their last positions; one with no such neighbour sits at the reference
        plus its matched neighbours' median displacement.
        """
        seen = matched >= 0
        new = np.where(seen[:, None], det[np.maximum(matched, 0)], self._cur)
        step_med, step_has = masked_median(_gather_rows(new - self._cur, self._graph),
                                           (seen & self._valid)[self._graph])
        pred = base + step_med
        if step_has.all():
            return pred, step_has
        total_med, total_has = masked_median(_gather_rows(new - self._ref, self._graph), seen[self._graph])
        pred = np.where(step_has[:, None], pred, self._ref + total_med)
        return pred, step_has | total_has

    def _area_checked(self, rows: np.ndarray, cols: np.ndarray, areas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pairs (marker rows (P,), detection cols (P,)) whose detection area (areas (M,)
        px^2) lies within `area_ratio_max` of the marker's reference area."""
        limit = self.params.area_ratio_max
        if limit == 0.0:
            return rows, cols
        ratio = areas[cols] / np.maximum(self._ref_areas[rows], 1e-9)
        ok = (ratio <= limit) & (ratio >= 1.0 / limit)
        return rows[ok], cols[ok]

    def _gated_round(
        self, pred: np.ndarray, det: np.ndarray, tree: cKDTree, areas: np.ndarray, gate: float,
        matched: np.ndarray, free: np.ndarray,
    ) -> int:
        """Assign unmatched markers (predicted at pred (N, 2) px) to free detections within `gate` px.

        tree: cKDTree of det (M, 2) px; areas: (M,) px^2. A marker takes its nearest free
        candidate when it is that detection's closest claimant; the markers left over are
        solved by scipy.optimize.linear_sum_assignment over their free candidates. Pairs
        failing the area check are dropped. Updates `matched` (N,) and `free` (M,) in place
        and returns the number of new matches.
        """
        todo = np.flatnonzero(matched < 0)
        m = det.shape[0]
        if todo.size == 0 or not free.any():
            return 0
        # With every detection free the nearest one is the first usable candidate; the
        # other candidates are needed only by markers that lose their nearest one.
        k = 1 if free.all() else min(_ROUND_CANDIDATES, m)
        dist, idx = tree.query(pred[todo], k=k, distance_upper_bound=gate)
        dist, idx = dist.reshape(todo.size, k), idx.reshape(todo.size, k)
        usable = idx < m
        if k > 1:
            usable[usable] = free[idx[usable]]
        has = usable.any(axis=1)
        if not has.any():
            return 0
        if not has.all():
            todo, dist, idx, usable = todo[has], dist[has], idx[has], usable[has]
        first = usable.argmax(axis=1) if k > 1 else np.zeros(todo.size, dtype=np.intp)
        rows_all = np.arange(todo.size)
        best_col = idx[rows_all, first]
        # Each candidate claimed once (the usual case) needs no ranking of the claimants.
        if np.bincount(best_col, minlength=m).max() <= 1:
            rows, cols, lost = todo, best_col, todo[:0]
        else:
            order = np.lexsort((dist[rows_all, first], best_col))
            winner = np.ones(order.size, dtype=bool)
            winner[1:] = best_col[order[1:]] != best_col[order[:-1]]
            won = order[winner]
            rows, cols = todo[won], best_col[won]
            lost = order[~winner]
        if lost.size:
            taken = np.zeros(m, dtype=bool)
            taken[cols] = True
            lost_idx = idx[lost]
            if k == 1:
                k = min(_ROUND_CANDIDATES, m)
                _, lost_idx = tree.query(pred[todo[lost]], k=k, distance_upper_bound=gate)
                lost_idx = lost_idx.reshape(lost.size, k)
            cand = lost_idx < m
            cand[cand] = free[lost_idx[cand]] & ~taken[lost_idx[cand]]
            rest_cols = np.unique(lost_idx[cand])
            if rest_cols.size:
                rest_rows = todo[lost]
                cost = np.linalg.norm(pred[rest_rows, None, :] - det[None, rest_cols, :], axis=2)
                cost = np.where(cost < gate, cost, 1e6 * gate)
                r, c = linear_sum_assignment(cost)
                ok = cost[r, c] < gate
                rows = np.concatenate([rows, rest_rows[r[ok]]])
                cols = np.concatenate([cols, rest_cols[c[ok]]])
        rows, cols = self._area_checked(rows, cols, areas)
        matched[rows] = cols
        free[cols] = False
        return int(rows.size)

    def _grow(
        self, pred: np.ndarray, base: np.ndarray, det: np.ndarray, tree: cKDTree, areas: np.ndarray
    ) -> np.ndarray:
        """(N,) int64 detection index per marker (-1 = none), grown outwards from `pred` (N, 2) px.

        Strict-gate rounds alternate with re-predicting unmatched markers from their matched
        neighbours; a last round uses the wider gate; matches that disagree with their
        neighbours (`neighbour_consistency`) are dropped.
        """
        p = self.params
        matched = np.full(self._ref.shape[0], -1, dtype=np.int64)
        free = np.ones(det.shape[0], dtype=bool)
        strict_gate = p.strict_gate_ratio * self.pitch_px
        for _ in range(p.rounds):
            if self._gated_round(pred, det, tree, areas, strict_gate, matched, free) == 0 or np.all(matched >= 0):
                break
            pred_next, has = self._neighbour_prediction(matched, det, base)
            pred = np.where(has[:, None], pred_next, pred)
        self._gated_round(pred, det, tree, areas, p.gate_ratio * self.pitch_px, matched, free)
        new = det[np.maximum(matched, 0)] - self._ref
        for _ in range(_PLAUSIBILITY_PASSES):
            bad = _inconsistent(new, matched >= 0, self._graph, self._spacing, p.tolerance_ratio)
            if not bad.any():
                break
            matched[bad] = -1
        return matched

    def _base_prediction(self) -> np.ndarray:
        """(N, 2) px: the last position of markers seen last frame; for the others the
        reference plus their seen neighbours' median displacement (the last position when none)."""
        if self._valid.all():
            return self._cur.copy()
        last_total = np.where(self._valid[:, None], self._cur - self._ref, 0.0)
        total_med, total_has = masked_median(_gather_rows(last_total, self._graph), self._valid[self._graph])
        lost = np.where(total_has[:, None], self._ref + total_med, self._cur)
        return np.where(self._valid[:, None], self._cur, lost)

    def _transport_prediction(self, base: np.ndarray, det: np.ndarray, radius: float) -> np.ndarray:
        """(N, 2) px: `base` moved by the median step of the global one-to-one matching
        (`_transport`) over each marker and its neighbours (the median drops single wrong pairs)."""
        cols = _transport(base, det, radius)
        paired = cols >= 0
        step = np.where(paired[:, None], det[np.maximum(cols, 0)] - base, 0.0)
        around = np.hstack([np.arange(base.shape[0])[:, None], self._graph])
        median, has = masked_median(_gather_rows(step, around), paired[around])
        return np.where(has[:, None], base + median, base)

    def _reacquire(
        self, matched: np.ndarray, base: np.ndarray, det: np.ndarray, areas: np.ndarray, radius: float
    ) -> np.ndarray:
        """`matched` (N,) with unmatched markers paired to free detections (det (M, 2) px,
        areas (M,) px^2) less than `radius` px from their `base` (N, 2) px prediction.

        Pairs are one-to-one with the least sum of squared distances
        (scipy.optimize.linear_sum_assignment) and pass the area check; a new pair that
        disagrees with its neighbours (`neighbour_consistency`) is dropped. This catches a
        marker that moved much farther than its neighbours (an edge or corner slipping
        over the skin) without the global fallback.
        """
        lost = np.flatnonzero(matched < 0)
        free = np.ones(det.shape[0], dtype=bool)
        free[matched[matched >= 0]] = False
        spare = np.flatnonzero(free)
        gap = base[lost, None, :] - det[None, spare, :]
        cost = np.einsum("ijk,ijk->ij", gap, gap)
        within = cost < radius * radius
        if not within.any():
            return matched
        r, c = linear_sum_assignment(np.where(within, cost, 2.0 * radius * radius * lost.size))
        ok = within[r, c]
        rows, cols = self._area_checked(lost[r[ok]], spare[c[ok]], areas)
        if rows.size == 0:
            return matched
        trial = matched.copy()
        trial[rows] = cols
        bad = _inconsistent(det[np.maximum(trial, 0)] - self._ref, trial >= 0, self._graph, self._spacing,
                            self.params.tolerance_ratio)
        trial[rows[bad[rows]]] = -1
        return trial

    def _match_assignment(self, det: np.ndarray, areas: np.ndarray) -> np.ndarray:
        """One-to-one matching grown from the velocity prediction; when that leaves many
        markers and detections unmatched (`TrackerParams.transport_edge_share`), also from
        the global one-to-one matching without velocity (`_transport`), keeping whichever
        matches more markers; when it leaves a few, those are re-acquired locally
        (`_reacquire`)."""
        p = self.params
        if det.shape[0] == 0:
            return np.full(self._ref.shape[0], -1, dtype=np.int64)
        tree = cKDTree(det)
        base = self._base_prediction()
        pred = base + self._velocity if p.use_velocity else base
        matched = self._grow(pred, base, det, tree, areas)
        radius = p.transport_ratio * self.pitch_px
        unmatched = np.count_nonzero(matched < 0)
        # A lattice matched one pitch off leaves markers at one edge and detections at the
        # other unmatched, however far apart: enough unmatched pairs call for the global match.
        unpaired = min(unmatched, det.shape[0] - (self._ref.shape[0] - unmatched))
        if radius > 0.0 and unpaired >= self._transport_trigger:
            other = self._grow(self._transport_prediction(base, det, radius), base, det, tree, areas)
            margin = self._transport_trigger if self.cluttered else 1
            if np.count_nonzero(other < 0) <= unmatched - margin:
                return other
        elif radius > 0.0 and unpaired > 0:
            return self._reacquire(matched, base, det, areas, radius)
        return matched
