"""Pictures of the tactile pipeline for people: the camera frame with the tracked markers
and their displacement arrows, the dense displacement field as a colour map with a quiver
(as in the paper's Fig. 2 and 3), and a strip chart of the slip probability over time.

Every drawing function takes plain arrays and returns a new (H, W, 3) uint8 BGR image on a
dark background; inputs are never modified. Non-finite values (NaN, inf) are skipped and
empty inputs give a labelled notice panel: a live view must never die on one bad message.
`fit`, `titled`, `hstack` and `vstack` assemble panels into one picture.
"""
from __future__ import annotations

import collections
import math

import cv2
import numpy as np

BACKGROUND = (34, 30, 30)  # BGR of every panel's background
TEXT = (225, 225, 225)
MUTED = (140, 140, 140)
GRID = (75, 70, 70)
TRACKED = (90, 220, 90)  # marker found in this frame
LOST = (70, 70, 235)  # marker not found (drawn at its last position)
ARROW = (0, 200, 255)  # displacement arrows on the camera frame
OUTLINE = (20, 20, 20)  # drawn under arrows so they show on light and dark backgrounds
CURVE = (255, 190, 60)  # slip probability line
SLIP_FILL = (52, 46, 100)  # time spans decided as slip (a dim red)
FONT = cv2.FONT_HERSHEY_SIMPLEX
SHIFT = 4  # cv2 drawing precision: coordinates carry 4 fractional bits (1/16 px)
COORD_LIMIT_PX = 1e5  # drawing coordinates are clipped to +-this (cv2 needs int32)
MIN_ARROW_PX = 1.5  # shorter arrows are drawn as nothing (field) or as the marker dot only


def _pt(x: float, y: float) -> tuple[int, int]:
    """A cv2 point with SHIFT fractional bits."""
    s, lim = 1 << SHIFT, COORD_LIMIT_PX
    return round(min(max(float(x), -lim), lim) * s), round(min(max(float(y), -lim), lim) * s)


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.45, colour=TEXT,
          thickness: int = 1) -> None:
    cv2.putText(img, text, org, FONT, scale, colour, thickness, cv2.LINE_AA)


def _text_width(text: str, scale: float = 0.45, thickness: int = 1) -> int:
    return cv2.getTextSize(text, FONT, scale, thickness)[0][0]


def as_bgr(image: np.ndarray, encoding: str = "") -> np.ndarray:
    """A BGR copy of a camera image.

    Args:
        image: (H, W) or (H, W, 1) uint8 grey, or (H, W, 3) uint8 colour.
        encoding: "rgb8" when a 3-channel image is RGB; anything else means BGR or grey.
    Returns:
        (H, W, 3) uint8 BGR (a new array).
    """
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"image dtype {image.dtype} is not uint8")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image shape {image.shape} is not (H, W), (H, W, 1) or (H, W, 3)")
    return cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if encoding == "rgb8" else image.copy()


def notice_panel(text: str, height_px: int = 240, width_px: int = 320) -> np.ndarray:
    """A blank panel with `text` centred: what to show when there is nothing to draw.

    Returns:
        (height_px, width_px, 3) uint8 BGR.
    """
    out = np.empty((height_px, width_px, 3), np.uint8)
    out[:] = BACKGROUND
    x = (width_px - _text_width(text, 0.5)) // 2
    _text(out, text, (max(x, 4), height_px // 2 + 5), 0.5, MUTED)
    return out


def _font_scale(height_px: int, base: float = 0.42) -> float:
    """Text size for a picture `height_px` tall, so that labels stay readable when a
    tall picture is shown scaled down to about 360 px."""
    return base * max(1.0, height_px / 360)


def _legend_band(img: np.ndarray, text: str) -> None:
    """A translucent band along the bottom edge of `img` with `text` (in place)."""
    fs = _font_scale(img.shape[0])
    h = round(48 * fs)
    band = img[-h:]
    band[:] = (band.astype(np.uint16) * 2 // 5).astype(np.uint8)
    _text(img, text, (round(14 * fs), img.shape[0] - round(14 * fs)), fs)


def draw_markers(image: np.ndarray, ref_px: np.ndarray, cur_px: np.ndarray, valid: np.ndarray | None = None,
                 *, arrow_scale: float = 3.0, zoom: float = 1.0, encoding: str = "",
                 legend: bool = True) -> np.ndarray:
    """The camera frame with each marker's displacement arrow and current position.

    An arrow starts at the marker's reference position and points along its displacement
    (cur - ref), lengthened `arrow_scale` times; tracked markers get a green dot at their
    current position, lost ones a red ring at their last position and no arrow.

    Args:
        image: (H, W) or (H, W, 3) uint8 camera frame (see `as_bgr`).
        ref_px: (N, 2) reference marker positions x, y in image px.
        cur_px: (N, 2) current marker positions x, y in image px.
        valid: (N,) bool, the marker was tracked in this frame (None: all).
        arrow_scale: arrow length per px of displacement.
        zoom: output size / image size; drawing after zooming keeps thin lines crisp.
        encoding: the image's encoding ("rgb8" for RGB).
        legend: write the tracked count and the arrow scale along the bottom edge.
    Returns:
        (round(H * zoom), round(W * zoom), 3) uint8 BGR; a 240x320 notice panel for an
        empty image.
    """
    if np.asarray(image).size == 0:
        return notice_panel("empty image")
    out = as_bgr(image, encoding)
    if zoom <= 0 or not math.isfinite(zoom):
        raise ValueError(f"zoom {zoom} must be a positive number")
    if zoom != 1.0:
        size = (max(1, round(out.shape[1] * zoom)), max(1, round(out.shape[0] * zoom)))
        out = cv2.resize(out, size, interpolation=cv2.INTER_LINEAR)
    ref = np.asarray(ref_px, np.float64).reshape(-1, 2)
    cur = np.asarray(cur_px, np.float64).reshape(-1, 2)
    if len(ref) != len(cur):
        raise ValueError(f"ref_px has {len(ref)} markers, cur_px {len(cur)}")
    ok = np.ones(len(ref), bool) if valid is None else np.asarray(valid, bool).reshape(-1)
    if len(ok) != len(ref):
        raise ValueError(f"valid has {len(ok)} entries for {len(ref)} markers")
    finite_cur = np.isfinite(cur).all(axis=1)
    finite_both = finite_cur & np.isfinite(ref).all(axis=1)
    radius = max(1.5, 1.6 * math.sqrt(zoom))
    thickness = 2 if out.shape[0] >= 400 else 1  # pictures this tall are usually shown scaled down
    for (rx, ry), (cx, cy), tracked, fin_c, fin_b in zip((ref * zoom).tolist(), (cur * zoom).tolist(), ok.tolist(),
                                                         finite_cur.tolist(), finite_both.tolist()):
        if not fin_c:
            continue
        if not tracked:
            cv2.circle(out, _pt(cx, cy), int(radius * 1.3 * (1 << SHIFT)), LOST, 1, cv2.LINE_AA, SHIFT)
            continue
        cv2.circle(out, _pt(cx, cy), int(radius * (1 << SHIFT)), TRACKED, -1, cv2.LINE_AA, SHIFT)
        if fin_b:
            tip_x, tip_y = rx + arrow_scale * (cx - rx), ry + arrow_scale * (cy - ry)
            length = math.hypot(tip_x - rx, tip_y - ry)
            if length >= MIN_ARROW_PX:
                tip = min(0.3, 4.0 * math.sqrt(zoom) / length)
                p0, p1 = _pt(rx, ry), _pt(tip_x, tip_y)
                cv2.arrowedLine(out, p0, p1, OUTLINE, thickness + 2, cv2.LINE_AA, SHIFT, tipLength=tip)
                cv2.arrowedLine(out, p0, p1, ARROW, thickness, cv2.LINE_AA, SHIFT, tipLength=tip)
    if legend:
        _legend_band(out, f"markers {int((ok & finite_cur).sum())}/{len(ref)} tracked   arrows x{arrow_scale:g}")
    return out


def field_range_px(magnitude_px: np.ndarray, min_range_px: float = 1.0) -> float:
    """The colour scale's top for auto ranging: the largest finite magnitude, but at least
    `min_range_px` so that sensor noise on an untouched skin does not fill the map (px)."""
    mag = np.asarray(magnitude_px, np.float64)
    finite = mag[np.isfinite(mag)]
    return max(float(finite.max()) if finite.size else 0.0, min_range_px)


def render_field(field: np.ndarray, grid_x_px: np.ndarray | None = None, grid_y_px: np.ndarray | None = None, *,
                 valid: bool = True, range_px: float = 0.0, min_range_px: float = 1.0, height_px: int = 360,
                 width_px: int = 0, arrow_step: int = 0, colormap: int = cv2.COLORMAP_VIRIDIS) -> np.ndarray:
    """The displacement field as a colour map of its magnitude with direction arrows and a
    colour bar in px.

    Args:
        field: (H, W, 3) float, channels dx, dy, magnitude in px (a `DisplacementField`).
        grid_x_px: (W,) x of each grid column in image px; with grid_y_px it sets the
            map's aspect ratio (None: square cells).
        grid_y_px: (H,) y of each grid row in image px.
        valid: False dims the map and marks it invalid.
        range_px: magnitude at the top of the colour scale in px (<= 0: auto, see
            `field_range_px`).
        min_range_px: lower bound of the auto range in px.
        height_px: output height.
        width_px: output width (0: the map's width plus the colour bar).
        arrow_step: one arrow every this many grid cells (0: about 15 arrows across).
        colormap: an OpenCV colour map id.
    Returns:
        (height_px, width_px or auto, 3) uint8 BGR. Arrows point along (dx, dy) in image
        axes (y down); an arrow as long as the arrow spacing means `range_px`.
    """
    field = np.asarray(field, np.float64)
    if field.ndim != 3 or field.shape[2] < 3:
        raise ValueError(f"field shape {field.shape} is not (H, W, 3)")
    gh, gw = field.shape[:2]
    fs = _font_scale(height_px, 0.38)
    bar_w, label_w, pad = 14, round(140 * fs), 8
    map_h = height_px - 2 * pad
    aspect = 1.0
    if grid_x_px is not None and grid_y_px is not None and len(grid_x_px) == gw > 1 and len(grid_y_px) == gh > 1:
        span_x = float(grid_x_px[-1]) - float(grid_x_px[0])
        span_y = float(grid_y_px[-1]) - float(grid_y_px[0])
        if math.isfinite(span_x) and math.isfinite(span_y) and span_x > 0 and span_y > 0:
            # W columns span W - 1 cell widths between the first and last grid x
            aspect = (span_x * gw / (gw - 1)) / (span_y * gh / (gh - 1))
    elif gh and gw:
        aspect = gw / gh
    aspect = float(np.clip(aspect, 0.5, 2.0))
    map_w = max(8, round(map_h * aspect))
    natural_w = pad + map_w + pad + bar_w + label_w
    width_px = width_px or natural_w
    if gh == 0 or gw == 0 or map_h < 8:
        return notice_panel("empty field", height_px, width_px)
    out = np.empty((height_px, natural_w, 3), np.uint8)
    out[:] = BACKGROUND
    mag = field[..., 2]
    finite = np.isfinite(mag)
    top = range_px if range_px > 0 else field_range_px(mag, min_range_px)
    level = np.where(finite, np.clip(mag / top, 0.0, 1.0), 0.0)
    level_img = cv2.resize((level * 255).astype(np.float32), (map_w, map_h), interpolation=cv2.INTER_LINEAR)
    coloured = cv2.applyColorMap(np.clip(level_img, 0, 255).astype(np.uint8), colormap)
    missing = cv2.resize((~finite).astype(np.uint8), (map_w, map_h), interpolation=cv2.INTER_NEAREST).astype(bool)
    coloured[missing] = GRID
    x0, y0 = pad, pad
    roi = out[y0:y0 + map_h, x0:x0 + map_w]
    roi[:] = coloured
    step = arrow_step or max(1, round(max(gh, gw) / 15))
    cell_w, cell_h = map_w / gw, map_h / gh
    full_px = 0.9 * step * min(cell_w, cell_h)
    dxdy = field[..., :2]
    for i in range(step // 2, gh, step):
        for j in range(step // 2, gw, step):
            dx, dy = dxdy[i, j].tolist()
            if not (math.isfinite(dx) and math.isfinite(dy)):
                continue
            vx, vy = dx / top * full_px, dy / top * full_px
            length = math.hypot(vx, vy)
            if length < MIN_ARROW_PX:
                continue
            if length > 1.3 * full_px:  # beyond the colour scale (fixed range): cap, keep direction
                vx, vy = vx * 1.3 * full_px / length, vy * 1.3 * full_px / length
                length = 1.3 * full_px
            cx, cy = (j + 0.5) * cell_w, (i + 0.5) * cell_h
            p0, p1 = _pt(cx - vx / 2, cy - vy / 2), _pt(cx + vx / 2, cy + vy / 2)
            tip = min(0.45, 5.0 / length)
            cv2.arrowedLine(roi, p0, p1, OUTLINE, 3, cv2.LINE_AA, SHIFT, tipLength=tip)
            cv2.arrowedLine(roi, p0, p1, (255, 255, 255), 1, cv2.LINE_AA, SHIFT, tipLength=tip)
    cv2.rectangle(out, (x0 - 1, y0 - 1), (x0 + map_w, y0 + map_h), GRID, 1)
    if not valid:
        roi[:] = (roi.astype(np.uint16) * 2 // 5).astype(np.uint8)
        msg = "invalid field"
        _text(roi, msg, ((map_w - _text_width(msg, 0.6, 2)) // 2, map_h // 2), 0.6, LOST, 2)
    _colour_bar(out, x0 + map_w + pad, y0, bar_w, map_h, top, colormap, fs)
    if width_px != natural_w:
        out = fit(out, height_px, width_px)
    return out


def _colour_bar(img: np.ndarray, x: int, y: int, w: int, h: int, top_px: float, colormap: int,
                font_scale: float) -> None:
    """A vertical colour bar, `top_px` at its top and 0 at its bottom, with ticks in px (in place)."""
    ramp = np.linspace(255, 0, h).astype(np.uint8)[:, None].repeat(w, axis=1)
    img[y:y + h, x:x + w] = cv2.applyColorMap(ramp, colormap)
    cv2.rectangle(img, (x - 1, y - 1), (x + w, y + h), GRID, 1)
    for frac in (0.0, 0.25, 0.5, 0.75, 1.0):
        ty = y + round((1 - frac) * (h - 1))
        cv2.line(img, (x + w, ty), (x + w + 3, ty), MUTED, 1)
        value = frac * top_px
        label = (f"{value:.2f}" if top_px < 2 else f"{value:.1f}") + (" px" if frac == 1.0 else "")
        half = round(11 * font_scale)
        _text(img, label, (x + w + 6, min(max(ty + half, y + 2 * half), y + h)), font_scale, MUTED)


class SlipHistory:
    """The slip probability over the last `window_s` seconds, for a strip chart.

    Samples are (t_s, probability, slip) in arrival order; samples older than `window_s`
    behind the newest are dropped, and a time step backwards by more than one second (a
    bag played again, a restarted camera) starts the history afresh.
    """

    def __init__(self, window_s: float = 20.0) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s {window_s} must be > 0")
        self.window_s = window_s
        self._samples: collections.deque[tuple[float, float, bool]] = collections.deque()

    def add(self, t_s: float, probability: float, slip: bool) -> None:
        if self._samples and t_s < self._samples[-1][0] - 1.0:
            self._samples.clear()
        self._samples.append((float(t_s), float(probability), bool(slip)))
        while self._samples[0][0] < t_s - self.window_s:
            self._samples.popleft()

    def samples(self) -> list[tuple[float, float, bool]]:
        """The kept (t_s, probability, slip) samples, oldest first."""
        return list(self._samples)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """t_s (N,) float64, probability (N,) float64, slip (N,) bool."""
        s = self._samples
        return (np.fromiter((x[0] for x in s), np.float64, len(s)), np.fromiter((x[1] for x in s), np.float64, len(s)),
                np.fromiter((x[2] for x in s), bool, len(s)))

    def __len__(self) -> int:
        return len(self._samples)


def render_slip_strip(t_s: np.ndarray, probability: np.ndarray, slip: np.ndarray | None = None, *,
                      width_px: int = 640, height_px: int = 160, window_s: float = 10.0,
                      threshold: float = 0.5, now_s: float | None = None, font_scale: float = 1.0) -> np.ndarray:
    """A strip chart of the slip probability over the last `window_s` seconds.

    Args:
        t_s: (N,) sample times in s (any origin), increasing.
        probability: (N,) P(slip) in [0, 1]; non-finite samples break the line.
        slip: (N,) bool decisions; spans decided as slip are shaded (None: no shading).
        width_px, height_px: output size.
        window_s: time span shown, ending at `now_s`.
        threshold: the decision threshold, drawn as a dashed line.
        now_s: the right edge of the chart in s (None: the last sample, or 0).
        font_scale: text size and margins relative to the defaults.
    Returns:
        (height_px, width_px, 3) uint8 BGR.
    """
    t = np.asarray(t_s, np.float64).reshape(-1)
    p = np.asarray(probability, np.float64).reshape(-1)
    s = np.zeros(len(t), bool) if slip is None else np.asarray(slip, bool).reshape(-1)
    if not len(t) == len(p) == len(s):
        raise ValueError(f"t_s, probability and slip have {len(t)}, {len(p)}, {len(s)} samples")
    out = np.empty((height_px, width_px, 3), np.uint8)
    out[:] = BACKGROUND
    fs = font_scale
    small, big = 0.38 * fs, 0.45 * fs
    left, right, top, bottom = round(44 * fs), round(14 * fs), round(22 * fs), round(22 * fs)
    pw, ph = width_px - left - right, height_px - top - bottom
    if pw < 10 or ph < 10:
        return out
    finite_t = t[np.isfinite(t)]
    now = now_s if now_s is not None else (float(finite_t[-1]) if finite_t.size else 0.0)
    t0 = now - window_s

    def xy(ts: np.ndarray, ps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return left + (ts - t0) / window_s * pw, top + (1.0 - np.clip(ps, 0.0, 1.0)) * ph

    shown = np.isfinite(t) & (t <= now)
    inside = np.flatnonzero(shown & (t >= t0))
    if inside.size and inside[0] > 0 and shown[inside[0] - 1]:
        inside = np.concatenate([[inside[0] - 1], inside])  # the line enters from the left edge
    shown = np.zeros(len(t), bool)
    shown[inside] = True
    ts, ps, ss = t[shown], p[shown], s[shown]
    edges = np.diff(np.concatenate([[0], ss.astype(np.int8), [0]]))
    for first, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):  # runs of slip
        x_a = max(xy(ts[first:first + 1], ps[:1])[0][0], left)
        x_b = xy(ts[stop:stop + 1], ps[:1])[0][0] if stop < len(ts) else left + pw
        if x_b > x_a:
            cv2.rectangle(out, _pt(x_a, top), _pt(min(x_b, left + pw), top + ph), SLIP_FILL, -1, cv2.LINE_8,
                          SHIFT)
    for level in (0.0, 0.5, 1.0):
        y = top + round((1 - level) * ph)
        cv2.line(out, (left, y), (left + pw, y), GRID, 1)
        _text(out, f"{level:g}", (left - round(8 * fs) - _text_width(f"{level:g}", small), y + round(4 * fs)), small,
              MUTED)
    if 0.0 < threshold < 1.0:
        y = top + (1 - threshold) * ph
        for x in np.arange(left, left + pw, 10.0):
            cv2.line(out, _pt(x, y), _pt(min(x + 5, left + pw), y), (90, 90, 200), 1, cv2.LINE_AA, SHIFT)
    tick_s = _nice_step(window_s / 5)
    for k in range(int(math.floor(window_s / tick_s)) + 1):
        x = left + pw - k * tick_s / window_s * pw
        cv2.line(out, (round(x), top + ph), (round(x), top + ph + 3), MUTED, 1)
        label = "now" if k == 0 else f"-{k * tick_s:g} s"
        _text(out, label, (max(left, round(x) - _text_width(label, small) // 2), height_px - round(5 * fs)), small,
              MUTED)
    xs, ys = xy(ts, ps)
    good = np.isfinite(ps)
    runs = np.split(np.arange(len(ts)), np.flatnonzero(~good))
    for run in runs:
        run = run[good[run]]
        if len(run) >= 2:
            pts = np.stack([xs[run], ys[run]], axis=1)
            pts[:, 0] = np.clip(pts[:, 0], left, left + pw)
            cv2.polylines(out, [np.round(pts * (1 << SHIFT)).astype(np.int32)], False, CURVE, max(2, round(2 * fs)),
                          cv2.LINE_AA, SHIFT)
        elif len(run) == 1 and xs[run[0]] >= left:
            cv2.circle(out, _pt(xs[run[0]], ys[run[0]]), 2 << SHIFT, CURVE, -1, cv2.LINE_AA, SHIFT)
    cv2.rectangle(out, (left, top), (left + pw, top + ph), GRID, 1)
    _text(out, "P(slip)", (left, round(15 * fs)), big)
    if len(ps) and math.isfinite(ps[-1]):
        label = f"{ps[-1]:.2f}  {'SLIP' if ss[-1] else 'no slip'}"
        _text(out, label, (left + pw - _text_width(label, big), round(15 * fs)), big, LOST if ss[-1] else TRACKED)
    return out


def _nice_step(raw: float) -> float:
    """1, 2 or 5 times a power of ten, the smallest not below `raw` (> 0)."""
    power = 10.0 ** math.floor(math.log10(raw))
    return next(m * power for m in (1, 2, 5, 10) if m * power >= raw)


def fit(image: np.ndarray, height_px: int, width_px: int) -> np.ndarray:
    """`image` scaled to fit (height_px, width_px) keeping its aspect ratio, centred on
    the background colour.

    Args:
        image: (H, W, 3) uint8 BGR.
    Returns:
        (height_px, width_px, 3) uint8 BGR.
    """
    out = np.empty((height_px, width_px, 3), np.uint8)
    out[:] = BACKGROUND
    h, w = image.shape[:2]
    if h == 0 or w == 0:
        return out
    scale = min(height_px / h, width_px / w)
    nh, nw = max(1, round(h * scale)), max(1, round(w * scale))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    y, x = (height_px - nh) // 2, (width_px - nw) // 2
    out[y:y + nh, x:x + nw] = cv2.resize(image, (nw, nh), interpolation=interp)
    return out


def titled(image: np.ndarray, title: str, font_scale: float = 1.0) -> np.ndarray:
    """`image` under a title bar.

    Returns:
        (H + 24 * font_scale, W, 3) uint8 BGR.
    """
    bar_px = round(24 * font_scale)
    bar = np.empty((bar_px, image.shape[1], 3), np.uint8)
    bar[:] = (50, 44, 44)
    _text(bar, title, (round(8 * font_scale), bar_px - round(8 * font_scale)), 0.48 * font_scale)
    return np.vstack([bar, image])


def _stack(panels: list[np.ndarray], gap_px: int, axis: int) -> np.ndarray:
    if not panels:
        raise ValueError("nothing to stack")
    across = max(p.shape[1 - axis] for p in panels)
    parts = []
    for k, panel in enumerate(panels):
        if panel.shape[1 - axis] < across:
            shape = list(panel.shape)
            shape[1 - axis] = across - panel.shape[1 - axis]
            filler = np.empty(shape, np.uint8)
            filler[:] = BACKGROUND
            panel = np.concatenate([panel, filler], axis=1 - axis)
        if k and gap_px:
            shape = list(panel.shape)
            shape[axis] = gap_px
            gap = np.empty(shape, np.uint8)
            gap[:] = (18, 16, 16)
            parts.append(gap)
        parts.append(panel)
    return np.concatenate(parts, axis=axis)


def hstack(panels: list[np.ndarray], gap_px: int = 4) -> np.ndarray:
    """Panels side by side, shorter ones padded at the bottom; (max H, sum W + gaps, 3)."""
    return _stack(panels, gap_px, axis=1)


def vstack(panels: list[np.ndarray], gap_px: int = 4) -> np.ndarray:
    """Panels one above the other, narrower ones padded on the right; (sum H + gaps, max W, 3)."""
    return _stack(panels, gap_px, axis=0)
