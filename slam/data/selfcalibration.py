"""The colour camera found from the data when nobody gives it: depth's occlusion edges against
colour's edges.

A two-camera sensor whose colour was not registered to depth shows it at every occlusion
boundary: the silhouette of a nearer object lies at one place in the depth image and a few
pixels away, a little larger or smaller, in the colour image. For the colour cameras met in
practice (focal lengths a few percent apart, principal points a few pixels apart, a baseline
of 2-3 cm whose parallax at room depths is a pixel or two) the colour pixel of a depth pixel
u is, to within that parallax, ``u_c = s (u - c) + c + t``: a scale s about the image centre c
and a shift t. ``estimate_color_warp`` finds s and t that bring the depth edges of several
frames onto the colour edges, scored by the chamfer distance (the mean distance from each
depth edge pixel to the nearest colour edge, truncated), every shift at once per scale
(OpenCV's template correlation of the warped depth edges with the colour edges' distance
transform). ``ColorWarp.apply`` resamples each frame's colour with it.

It is applied only when it is confident: the frames agree on it (their own best warps lie
close together), it beats identity clearly, and it is not at the edge of the search. On data
registered already, identity scores best and nothing changes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from slam.data.frame import Frame

SCALES = np.round(np.arange(0.80, 1.2001, 0.01), 4)
"""Scales searched (colour focal length over depth's)."""
MAX_SHIFT_FRACTION = 0.08
"""Shifts searched: up to this fraction of the image width, either way."""
CHAMFER_CAP_PX = 8.0
"""A depth edge farther than this from any colour edge counts as this far (an edge that one
image has and the other has not)."""
EDGE_PERCENT = 10.0
"""Colour edges: this share of the pixels, those with the steepest grey gradient (a share,
not a threshold, so that a dim or soft image has edges too)."""
MIN_GAIN = 0.15
"""The warp must bring the depth edges this much closer (relative chamfer) than identity."""
MAX_SPREAD_PX = 2.5
"""The warps found from either half of the frames (every other one) must agree within this
many pixels (the median distance between where they put the image's corners)."""
WORK_WIDTH = 320
"""Frames are compared at most this wide (the cost grows with the square of the width; the
thresholds below are in pixels at this width)."""
CALIBRATION_FRAMES = 20
"""Frames a sequence's colour camera is estimated from, spread over it."""
MIN_EDGE_PIXELS = 200
"""A frame with fewer depth edge pixels than this tells nothing and is left out."""


@dataclass(frozen=True)
class ColorWarp:
    """The colour image's warp from the depth image's pixels, ``u_c = scale (u - c) + c + shift``
    (c the image centre), how well it fits, and whether it is applied.

    chamfer_px / identity_chamfer_px: mean truncated distance of the frames' depth edges to
    the colour edges with this warp and with none; frames: frames used; spread_px: how far
    apart the answers of either half of the frames lie (all in the frames' own pixels); confidence in [0, 1]; applied:
    confident enough; reason: why, in words."""

    scale: float
    shift_x: float
    shift_y: float
    chamfer_px: float
    identity_chamfer_px: float
    frames: int
    spread_px: float
    confidence: float
    applied: bool
    reason: str

    def apply(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H, W, 3) resampled onto the depth image's pixels: each takes the colour at
        its warped place; returns it and (H, W) bool, the pixels whose place lies inside."""
        import cv2

        H, W = rgb.shape[:2]
        centre = np.array([(W - 1) / 2.0, (H - 1) / 2.0])
        offset = (1.0 - self.scale) * centre + [self.shift_x, self.shift_y]
        warp = np.array([[self.scale, 0.0, offset[0]], [0.0, self.scale, offset[1]]])
        out = cv2.warpAffine(np.ascontiguousarray(rgb, np.float32), warp, (W, H),
                             flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
        u, v = np.meshgrid(np.arange(W) * self.scale + offset[0], np.arange(H) * self.scale + offset[1])
        inside = (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)
        return out, inside

    def as_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def depth_edges(depth: np.ndarray, relative_jump: float = 0.05) -> np.ndarray:
    """(H, W) bool: valid depth pixels on the near side of an occlusion edge (a 4-neighbour
    farther by more than ``relative_jump`` of the depth, or without depth beside a valid one
    would be noise: only jumps between two measured depths count)."""
    d = depth.astype(np.float32)
    edge = np.zeros(d.shape, bool)
    for axis in (0, 1):
        a = d.take(range(0, d.shape[axis] - 1), axis=axis)
        b = d.take(range(1, d.shape[axis]), axis=axis)
        both = (a > 0) & (b > 0)
        a_near = both & (b - a > relative_jump * a)
        b_near = both & (a - b > relative_jump * b)
        if axis == 0:
            edge[:-1] |= a_near
            edge[1:] |= b_near
        else:
            edge[:, :-1] |= a_near
            edge[:, 1:] |= b_near
    return edge


def color_edge_distance(rgb: np.ndarray) -> np.ndarray:
    """(H, W) float32: each pixel's distance (px) to the nearest colour edge (the
    ``EDGE_PERCENT`` % of pixels with the steepest grey gradient), truncated at ``CHAMFER_CAP_PX``."""
    import cv2

    grey = cv2.cvtColor(np.clip(rgb, 0, 1).astype(np.float32), cv2.COLOR_RGB2GRAY)
    grey = cv2.GaussianBlur(grey, (3, 3), 0)
    magnitude = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
    edges = magnitude >= max(np.percentile(magnitude, 100 - EDGE_PERCENT), 1e-3)
    distance = cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, 3)
    return np.minimum(distance, CHAMFER_CAP_PX).astype(np.float32)


def _chamfer_over_shifts(points: np.ndarray, distance: np.ndarray, scale: float, max_shift: int) -> np.ndarray:
    """Mean truncated distance of the edge ``points`` (N, 2) x, y warped by ``scale`` about the
    image centre, for every integer shift in [-max_shift, max_shift]^2: (2m+1, 2m+1), row dy,
    column dx."""
    import cv2

    H, W = distance.shape
    centre = np.array([(W - 1) / 2.0, (H - 1) / 2.0])
    warped = np.rint(scale * (points - centre) + centre).astype(np.int64)
    m = max_shift
    # The template: the warped edge points on a canvas the image's size plus the margin
    # (points outside it cannot be scored at any shift and count as the cap).
    canvas = np.zeros((H + 2 * m, W + 2 * m), np.float32)
    keep = (warped[:, 0] >= -m) & (warped[:, 0] < W + m) & (warped[:, 1] >= -m) & (warped[:, 1] < H + m)
    np.add.at(canvas, (warped[keep, 1] + m, warped[keep, 0] + m), 1.0)
    padded = cv2.copyMakeBorder(distance, 2 * m, 2 * m, 2 * m, 2 * m, cv2.BORDER_CONSTANT, value=CHAMFER_CAP_PX)
    total = cv2.matchTemplate(padded, canvas, cv2.TM_CCORR)  # (2m+1, 2m+1): sum of distance under each shift
    lost = (~keep).sum() * CHAMFER_CAP_PX
    return (total + lost) / max(len(points), 1)


@dataclass(frozen=True)
class _FrameEdges:
    points: np.ndarray  # (N, 2) x, y of depth edge pixels
    distance: np.ndarray  # (H, W) colour edges' distance transform


def _working_size(frame: Frame) -> tuple[int, int]:
    """(width, height) the estimate works at: the frame's, shrunk to ``WORK_WIDTH`` wide."""
    height, width = frame.depth.shape
    if width <= WORK_WIDTH:
        return width, height
    return WORK_WIDTH, max(1, int(round(height * WORK_WIDTH / width)))


def _frame_edges(frame: Frame) -> _FrameEdges | None:
    import cv2

    size = _working_size(frame)
    depth, rgb, valid = frame.depth, frame.rgb, frame.color_valid
    if size != (depth.shape[1], depth.shape[0]):
        depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        rgb = cv2.resize(np.ascontiguousarray(rgb, np.float32), size, interpolation=cv2.INTER_AREA)
        valid = None if valid is None else cv2.resize(valid.astype(np.uint8), size,
                                                      interpolation=cv2.INTER_NEAREST).astype(bool)
    edges = depth_edges(depth)
    if valid is not None:
        edges &= valid
    ys, xs = np.nonzero(edges)
    if len(xs) < MIN_EDGE_PIXELS:
        return None
    return _FrameEdges(np.stack([xs, ys], 1).astype(np.float64), color_edge_distance(rgb))


def _best(cost: np.ndarray, max_shift: int) -> tuple[int, float, float, float]:
    """(scale index, dx, dy, cost) of the lowest cost over (scales, dy, dx), the shift refined
    to a sub-pixel by a parabola through the neighbours."""
    k, iy, ix = np.unravel_index(int(np.argmin(cost)), cost.shape)

    def refine(values: np.ndarray, i: int) -> float:
        if 0 < i < len(values) - 1:
            a, b, c = values[i - 1], values[i], values[i + 1]
            denominator = a - 2 * b + c
            if denominator > 1e-9:
                return i + 0.5 * (a - c) / denominator
        return float(i)

    dx = refine(cost[k, iy, :], ix) - max_shift
    dy = refine(cost[k, :, ix], iy) - max_shift
    return int(k), float(dx), float(dy), float(cost[k, iy, ix])


def _refined_scale(costs: np.ndarray, k: int) -> float:
    """The scale at index ``k`` of ``SCALES`` refined by a parabola through its neighbours' costs."""
    if 0 < k < len(costs) - 1:
        a, b, c = costs[k - 1], costs[k], costs[k + 1]
        denominator = a - 2 * b + c
        if denominator > 1e-9:
            step = SCALES[1] - SCALES[0]
            return float(SCALES[k] + step * float(np.clip(0.5 * (a - c) / denominator, -0.5, 0.5)))
    return float(SCALES[k])


def _corner_distance(a: tuple[float, float, float], b: tuple[float, float, float], width: int, height: int) -> float:
    """Median distance (px) between where two warps (scale, dx, dy) put the image's corners."""
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], np.float64)
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])

    def warp(w):
        return w[0] * (corners - centre) + centre + [w[1], w[2]]

    return float(np.median(np.linalg.norm(warp(a) - warp(b), axis=1)))


def estimate_color_warp(frames: list[Frame]) -> ColorWarp:
    """The colour image's warp (scale about the centre, shift) that lays the depth edges of
    ``frames`` (a handful spread over a sequence, all of one size) onto their colour edges;
    applied when either half of the frames finds about the same and it beats identity clearly
    (module doc); fewer than 4 usable frames are never confident."""
    usable = [e for e in (_frame_edges(f) for f in frames) if e is not None]
    # Shifts are found in working pixels and reported in the frames' own.
    to_native = frames[0].depth.shape[1] / _working_size(frames[0])[0] if frames else 1.0
    if not usable:
        return ColorWarp(1.0, 0.0, 0.0, float("nan"), float("nan"), 0, float("nan"), 0.0, False,
                         "no frame has enough depth edges to compare with colour")
    H, W = usable[0].distance.shape
    m = max(1, int(round(MAX_SHIFT_FRACTION * W)))
    per_frame = np.stack([np.stack([_chamfer_over_shifts(e.points, e.distance, s, m) for s in SCALES])
                          for e in usable])  # (F, scales, 2m+1, 2m+1)
    weights = np.array([len(e.points) for e in usable], np.float64)

    def joint_answer(rows) -> tuple[tuple[float, float, float], float, np.ndarray]:
        joint = np.tensordot(weights[rows] / weights[rows].sum(), per_frame[rows], axes=1)
        k, dx, dy, cost = _best(joint, m)
        return (_refined_scale(joint[:, int(round(dy)) + m, int(round(dx)) + m], k), dx, dy), cost, joint

    everything = np.arange(len(usable))
    answer, best, joint = joint_answer(everything)
    k = int(np.argmin(np.abs(SCALES - answer[0])))
    dx, dy = answer[1], answer[2]
    identity = float(joint[int(np.argmin(np.abs(SCALES - 1.0))), m, m])
    # Agreement: the answers of the two halves of the frames (every other one), each found jointly.
    if len(usable) >= 4:
        half_a, _, _ = joint_answer(everything[0::2])
        half_b, _, _ = joint_answer(everything[1::2])
        spread = _corner_distance(half_a, half_b, W, H)
    else:
        spread = float("inf")
    gain = (identity - best) / identity if identity > 0 else 0.0
    at_edge = k in (0, len(SCALES) - 1) or max(abs(dx), abs(dy)) >= m - 0.5
    confidence = float(np.clip(gain / (2 * MIN_GAIN), 0, 1) * np.clip(1.5 - spread / MAX_SPREAD_PX, 0, 1)
                       * (0.0 if at_edge else 1.0))
    if _corner_distance(answer, (1.0, 0.0, 0.0), W, H) < 1.0:
        reason, applied = "registered already: identity is the best warp within a pixel", False
    elif at_edge:
        reason, applied = "the best warp lies at the edge of the search: not trusted", False
    elif gain < MIN_GAIN:
        reason, applied = f"the warp brings edges only {gain:.0%} closer than identity (needs {MIN_GAIN:.0%})", False
    elif spread > MAX_SPREAD_PX:
        reason, applied = f"the frames disagree by {spread:.1f} px at {W} px wide (at most {MAX_SPREAD_PX})", False
    else:
        reason, applied = f"edges {gain:.0%} closer than identity, the frames within {spread:.1f} px at {W} px wide", True
    return ColorWarp(answer[0], dx * to_native, dy * to_native, best * to_native, identity * to_native, len(usable),
                     spread * to_native, confidence, applied, reason)
