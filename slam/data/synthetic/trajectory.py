"""Camera trajectories through the synthetic scenes (world frame of ``scene``: z up).

Every kind is a fixed smooth path ``p(s)`` with a look-at target ``q(s)`` for ``s`` in [0, 1];
``n_frames`` only sets how finely it is sampled, so more frames mean smaller steps. At
:data:`NOMINAL_FRAMES` each room kind moves at most ~1.5 cm and ~1 degree per frame (handheld
motion at 30 Hz). The seed jitters radius, height, start angle, direction and mirroring.

The room paths stay in the free ring around the central table: horizontally at least 1 m from
every wall (furniture occupies only the 0.55 m band along them) and at least 0.45 m from the
table's footprint, at heights 1.3-1.6 m, looking at content 0.5-5 m away.

``laps`` is made for the ``hall`` scene (:data:`TRAJECTORY_SCENES`) of the same ``size``: two
anticlockwise laps along its ring corridor, about 18 m in the ``compact`` hall (the default) and
51 m in the ``large`` one, at most 2.5 cm and 1.5 degrees per frame at
:data:`LAPS_NOMINAL_FRAMES` (780 and 2200 frames); see :func:`_laps` and :data:`LAPS_STYLES`.

Poses are camera-to-world with OpenCV camera axes: x right, y down, z forward.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from slam.data.frame import DataError
from slam.data.synthetic.scene import HALL_LAYOUTS, HALL_SIZES, hall_size

TRAJECTORY_KINDS = ("orbit", "walk", "loop", "agents", "laps")
LAPS_NOMINAL_FRAMES = {"compact": 780, "large": 2200}
"""Frame count of ``laps`` per hall size at which it moves <= 2.5 cm and 1.5 deg per frame, for
every seed (seeds 0-29: compact 18.1-18.6 m, at most 2.44 cm and 1.39 deg per frame; large
50.6-51.1 m, 2.44 cm and 1.18 deg). The path and its speed profile are fixed, so per-frame motion
scales as 1 / frames: half the frames, twice the step."""
NOMINAL_FRAMES = {"orbit": 100, "walk": 100, "loop": 500, "agents": 100, "laps": LAPS_NOMINAL_FRAMES[HALL_SIZES[0]]}
"""Default frame count of each kind, at which it moves <= ~1.5 cm and ~1 deg per frame (``laps``:
<= 2.5 cm and 1.5 deg, for its default size ``compact``; see :func:`nominal_frames`)."""
TRAJECTORY_SCENES = {"orbit": "room", "walk": "room", "loop": "room", "agents": "room", "laps": "hall"}
"""The scene kind (``scene.make_scene``) each trajectory kind is made for; ``laps`` walks
the ``hall`` of its own ``size``."""
TABLE_TARGET = np.array([0.0, 0.0, 0.85])
"""Where inward-looking paths aim: just above the table top at the room centre."""
MAX_AGENTS = 8
WORLD_UP = (0.0, 0.0, 1.0)


def nominal_frames(kind: str, size: str | None = None) -> int:
    """The default frame count of ``kind`` (:data:`NOMINAL_FRAMES`); for ``laps``, that of its hall
    ``size`` (:data:`LAPS_NOMINAL_FRAMES`; None = ``compact``)."""
    if kind not in TRAJECTORY_KINDS:
        raise DataError(f"unknown synthetic trajectory kind {kind!r}; valid: {', '.join(TRAJECTORY_KINDS)}")
    if kind != "laps":
        if size is not None:
            raise DataError(f"trajectory size {size!r} applies only to kind 'laps', not {kind!r}")
        return NOMINAL_FRAMES[kind]
    return LAPS_NOMINAL_FRAMES[hall_size(size)]


def look_at(positions: np.ndarray, targets: np.ndarray, up: tuple[float, float, float] = WORLD_UP) -> np.ndarray:
    """Camera-to-world poses looking from ``positions`` at ``targets`` with no roll.

    Args:
        positions: (N, 3) camera centres.
        targets: (N, 3) points each camera looks at (optical axis through them).
        up: world up; the camera's y axis (down in the image) points against it.
    Returns:
        (N, 4, 4) float64 ``T_world_cam`` with OpenCV axes (x right, y down, z forward).
    """
    positions = np.asarray(positions, dtype=np.float64)
    forward = np.asarray(targets, dtype=np.float64) - positions
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    norm = np.linalg.norm(right, axis=1, keepdims=True)
    if np.any(norm < 1e-6):
        raise ValueError("look_at: a viewing direction is parallel to the up vector")
    right /= norm
    down = np.cross(forward, right)
    T = np.tile(np.eye(4), (len(positions), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = right, down, forward, positions
    return T


def _circle(theta: np.ndarray, radius: np.ndarray | float, height: np.ndarray | float) -> np.ndarray:
    """(N,) angles -> (N, 3) points on a horizontal circle about the room's vertical axis."""
    return np.stack([radius * np.cos(theta), radius * np.sin(theta), np.broadcast_to(height, theta.shape)], 1)


def _orbit(s: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A 0.95 rad arc (about 1.4 m) around the table, looking at it, bobbing 5 cm."""
    theta0 = rng.uniform(0, 2 * np.pi)
    sense = rng.choice([-1.0, 1.0])
    radius = rng.uniform(1.35, 1.5)
    height = rng.uniform(1.35, 1.55)
    phase = rng.uniform(0, 2 * np.pi)
    positions = _circle(theta0 + sense * 0.95 * s, radius, height + 0.05 * np.sin(2 * np.pi * s))
    wander = 0.08 * np.stack([np.sin(np.pi * s + phase), np.cos(np.pi * s + phase), np.zeros_like(s)], 1)
    return positions, TABLE_TARGET + wander


def _walk(s: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A 1.4 m gently curving walk along one long side of the table, looking ahead and
    turning a little towards the table midway; mirrored in x and/or y by the seed."""
    y0 = -1.25 + rng.uniform(-0.08, 0.08)
    height = rng.uniform(1.4, 1.55)
    x = -1.75 + 1.4 * s
    y = y0 - 0.12 * np.sin(np.pi * s)
    z = height + 0.03 * np.sin(3 * np.pi * s)
    heading = np.arctan2(-0.12 * np.pi * np.cos(np.pi * s), 1.4) + 0.3 * np.sin(np.pi * s)
    pitch = np.radians(rng.uniform(10, 18))
    look = np.stack([np.cos(heading) * np.cos(pitch), np.sin(heading) * np.cos(pitch),
                     np.full_like(s, -np.sin(pitch))], 1)
    positions = np.stack([x, y, z], 1)
    mirror = np.array([rng.choice([-1.0, 1.0]), rng.choice([-1.0, 1.0]), 1.0])
    return positions * mirror, (positions + 2.0 * look) * mirror


def _loop(s: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One full turn (about 6.3 m) on an ellipse around the table, looking at it slightly
    ahead of the motion; it widens by 8 % so the end is ~9 cm from the start, same heading."""
    theta0 = rng.uniform(0, 2 * np.pi)
    sense = rng.choice([-1.0, 1.0])
    a, b = rng.uniform(1.05, 1.12), rng.uniform(0.8, 0.85)
    height = rng.uniform(1.4, 1.5)
    theta = theta0 + sense * 2 * np.pi * s
    grow = 1.0 + 0.08 * s
    positions = np.stack([a * grow * np.cos(theta), b * grow * np.sin(theta),
                          height + 0.06 * np.sin(4 * np.pi * s)], 1)
    tangent = sense * np.stack([-a * np.sin(theta), b * np.cos(theta), np.zeros_like(s)], 1)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    return positions, TABLE_TARGET + 0.45 * tangent


LAPS = 2
"""Full turns of the ``laps`` path around the hall's block."""


@dataclass(frozen=True)
class LapsStyle:
    """How the ``laps`` path walks one hall size (``scene.HALL_LAYOUTS``); see :func:`_laps`.

    Lengths in metres; ``(amplitude, cycles per lap)`` pairs are sine swings along the lap
    coordinate (0 at the start, 1 after one lap, 2 at the end).

    Attributes:
        start_x: x of the start in the south corridor (+- ``start_jitter`` by seed).
        lane: distance of the first lap from the block's faces (+- 0.02 by seed).
        lane_shift, lower: the second lap runs this much farther out and lower.
        sway: side-to-side swing of the lane; ``bob``: up and down swing of the height.
        glance: look yaw swing (rad) about the smoothed heading, on the first and second lap.
        first_glance: phase of the first lap's glance (+- 0.4 by seed; > 0 turns left, to the block).
        pitch_cycles: cycles per lap of the pitch's +- 2 deg swing about 13 deg down.
        smoothing: sigma (m) of the Gaussian that smooths the heading of motion into the look
            direction, so the view eases into the corners.
        slow: time per metre is ``1 + slow * turn`` (turn: rad of look per metre), so the camera
            slows where the view turns fast.
    """

    start_x: float
    start_jitter: float
    lane: float
    lane_shift: float
    lower: float
    sway: tuple[float, float]
    bob: tuple[float, float]
    glance: tuple[tuple[float, float], tuple[float, float]]
    first_glance: float
    pitch_cycles: float
    smoothing: float
    slow: float


LAPS_STYLES: dict[str, LapsStyle] = {
    "compact": LapsStyle(start_x=-0.7, start_jitter=0.1, lane=0.63, lane_shift=0.10, lower=0.04,
                         sway=(0.02, 2.0), bob=(0.02, 3.0), glance=((0.15, 1.6), (0.18, 1.3)), first_glance=0.3,
                         pitch_cycles=1.7, smoothing=0.7, slow=0.05),
    "large": LapsStyle(start_x=-2.4, start_jitter=0.2, lane=1.02, lane_shift=0.15, lower=0.06,
                       sway=(0.03, 3.3), bob=(0.03, 5.3), glance=((0.2, 4.3), (0.24, 3.7)), first_glance=0.3,
                       pitch_cycles=2.9, smoothing=0.7, slow=0.15),
}
"""``compact``: lanes 0.63 and 0.73 m from the block in its 1.4 m corridors (>= 0.55 m from the
block's panels, >= 0.6 m from the outer walls), 4 cm lower on lap 2; whole cycles of sway and bob
per lap, so lap 2 runs parallel to lap 1, 10-14 cm from it. Its 0.8 and 1.6 m sides lie within the
0.7 m heading smoothing, so the view turns almost steadily (~40 deg/m) and hardly needs slowing.
``large``: lanes 1.02 and 1.17 m in 2.2 m corridors, 6 cm lower on lap 2."""
_LAPS_SAMPLES_PER_LAP = 20000
_LAPS_MARGIN = 0.1
"""The dense path extends this many laps beyond both ends so the look-direction filter has no edge."""


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _around_block(sigma: np.ndarray, offset: np.ndarray, half: tuple[float, float], radius: float) -> np.ndarray:
    """Points ``offset`` (N,) metres outside the rectangle |x| <= a, |y| <= b (``half``).

    ``sigma`` (N,) is arc length along the rectangle's offset curve at distance ``radius``,
    walked anticlockwise from the south-west end of the south side (x = -a, y = -b - radius),
    periodic in its perimeter. The base point moves along the sides and stays on the corners
    while the outward normal turns there, so each point is exactly ``offset`` from the block.

    Returns:
        (N, 2) float64 x, y.
    """
    a, b = half
    arc = radius * np.pi / 2
    # Side k runs from corner k-1 to corner k; corner k turns the normal by 90 deg.
    sides = [((-a, -b), (1.0, 0.0), 2 * a, (0.0, -1.0)), ((a, -b), (0.0, 1.0), 2 * b, (1.0, 0.0)),
             ((a, b), (-1.0, 0.0), 2 * a, (0.0, 1.0)), ((-a, b), (0.0, -1.0), 2 * b, (-1.0, 0.0))]
    lengths = np.array([x for side in sides for x in (side[2], arc)])
    starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    sigma = np.mod(sigma, lengths.sum())
    seg = np.clip(np.searchsorted(starts, sigma, side="right") - 1, 0, len(lengths) - 1)
    local = sigma - starts[seg]
    k, is_corner = seg // 2, seg % 2 == 1
    start = np.array([side[0] for side in sides])[k]
    along = np.array([side[1] for side in sides])[k]
    normal = np.array([side[3] for side in sides])[k]
    # Corner k sits at the end of side k; its normal turns from side k's to side k+1's.
    end = start + along * np.array([side[2] for side in sides])[k][:, None]
    phi = np.arctan2(normal[:, 1], normal[:, 0]) + local / radius
    base = np.where(is_corner[:, None], end, start + along * local[:, None])
    n = np.where(is_corner[:, None], np.stack([np.cos(phi), np.sin(phi)], 1), normal)
    return base + offset[:, None] * n


def _laps(s: np.ndarray, rng: np.random.Generator, size: str = "compact") -> tuple[np.ndarray, np.ndarray]:
    """Two anticlockwise laps along the ring corridor of the ``hall`` scene of ``size``.

    It starts in the south corridor heading +x (x ~ ``start_x``), ``lane`` from the block
    (compact: 0.63 m in a 1.4 m corridor, about 18 m in all; large: 1.02 m in 2.2 m, about 51 m)
    at 1.47 m height, and ends there after two full turns. Over the last 25 % of the first lap
    it moves ``lane_shift`` outwards and ``lower`` down, so the second lap revisits every place
    from a shifted viewpoint, and its side-to-side glance takes a different frequency and
    amplitude. The camera looks ahead along the corridor (the direction of motion, smoothed
    over ``smoothing`` so it eases into each corner), pitched 11-15 deg down, glancing towards
    the walls in slow swings; it slows where the view turns fast. The seed jitters start, lane,
    height and phases by a few cm / degrees. See :class:`LapsStyle` for the numbers.
    """
    style = LAPS_STYLES[size]
    x0 = style.start_x + rng.uniform(-style.start_jitter, style.start_jitter)
    lane = style.lane + rng.uniform(-0.02, 0.02)
    height = 1.47 + rng.uniform(-0.02, 0.02)
    phases = rng.uniform(0.0, 2 * np.pi, size=5)
    phases[2] = style.first_glance + rng.uniform(-0.4, 0.4)  # the first glance turns left (large: to the first cabinet)
    half = HALL_LAYOUTS[size].block_half_size
    radius = lane + style.lane_shift / 2
    perimeter = 4 * (half[0] + half[1]) + 2 * np.pi * radius
    # Dense lap coordinate u (0 .. LAPS = start .. end), extended on both sides.
    n_dense = int(_LAPS_SAMPLES_PER_LAP * (LAPS + 2 * _LAPS_MARGIN)) + 1
    u = np.linspace(-_LAPS_MARGIN, LAPS + _LAPS_MARGIN, n_dense)
    second = _smoothstep((u - 0.75) / 0.25)  # 0 on lap 1, 1 on lap 2
    offset = lane + style.lane_shift * second + style.sway[0] * np.sin(2 * np.pi * style.sway[1] * u + phases[0])
    xy = _around_block(x0 + half[0] + u * perimeter, offset, half, radius)
    z = height - style.lower * second + style.bob[0] * np.sin(2 * np.pi * style.bob[1] * u + phases[1])
    dense = np.concatenate([xy, z[:, None]], 1)
    # Resample on a uniform arc-length grid.
    ell = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    grid = np.linspace(ell[0], ell[-1], n_dense)
    step = grid[1] - grid[0]
    points = np.stack([np.interp(grid, ell, dense[:, k]) for k in range(3)], 1)
    u = np.interp(grid, ell, u)
    second = _smoothstep((u - 0.75) / 0.25)
    # Look direction: heading of motion smoothed by a Gaussian plus a glance.
    tangent = np.gradient(points[:, :2], axis=0)
    heading = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
    width = int(round(style.smoothing / step))
    kernel = np.exp(-0.5 * (np.arange(-3 * width, 3 * width + 1) / width) ** 2)
    heading = np.convolve(np.pad(heading, 3 * width, mode="edge"), kernel / kernel.sum(), mode="valid")
    (a1, f1), (a2, f2) = style.glance
    glance = ((1 - second) * a1 * np.sin(2 * np.pi * f1 * u + phases[2])
              + second * a2 * np.sin(2 * np.pi * f2 * u + phases[3]))
    yaw = heading + glance
    pitch = np.radians(13.0) + np.radians(2.0) * np.sin(2 * np.pi * style.pitch_cycles * u + phases[4])
    # Time: slower where the view turns fast (per metre), normalised over the real path u in [0, LAPS].
    turn = np.abs(np.gradient(yaw, step)) + np.abs(np.gradient(pitch, step))
    dt = (1.0 + style.slow * turn) * step
    inside = (u >= 0.0) & (u <= LAPS)
    first, last = np.flatnonzero(inside)[[0, -1]]
    time = np.concatenate([[0.0], np.cumsum(0.5 * (dt[1:] + dt[:-1]))])
    time = (time - time[first]) / (time[last] - time[first])
    where = np.interp(s, time, grid)
    positions = np.stack([np.interp(where, grid, points[:, k]) for k in range(3)], 1)
    yaw_s, pitch_s = np.interp(where, grid, yaw), np.interp(where, grid, pitch)
    look = np.stack([np.cos(yaw_s) * np.cos(pitch_s), np.sin(yaw_s) * np.cos(pitch_s), -np.sin(pitch_s)], 1)
    return positions, positions + 2.0 * look


def _agent(k: int, theta0: float, jitter: np.ndarray) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Agent ``k``'s 0.95 rad arc around the table, starting 0.5 rad after agent k-1's, so
    consecutive agents share half their arcs; odd agents walk it backwards."""
    def path(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        start = theta0 + 0.5 * k
        theta = start + 0.95 * (s if k % 2 == 0 else 1.0 - s)
        radius = 1.36 + 0.12 * (k % 2) + jitter[0]
        height = 1.38 + 0.08 * (k % 3) + jitter[1] + 0.04 * np.sin(2 * np.pi * s)
        return _circle(theta, radius, height), np.broadcast_to(TABLE_TARGET, (len(s), 3))
    return path


def _check_frames(n_frames: int) -> np.ndarray:
    """(N,) path parameters in [0, 1] for ``n_frames`` frames."""
    if not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise DataError(f"n_frames must be a positive integer, got {n_frames!r}")
    return np.linspace(0.0, 1.0, int(n_frames)) if n_frames > 1 else np.zeros(1)


def make_agent_trajectories(n_agents: int, n_frames: int, seed: int = 0) -> np.ndarray:
    """Trajectories of ``n_agents`` cameras mapping the room together.

    Each walks a 0.95 rad arc around the table, looking at it; agent k's arc starts 0.5 rad
    after agent k-1's (odd agents walk theirs backwards), so start poses differ while the paths
    overlap pairwise in the shared part of the room and all views share the table.

    Returns:
        (A, N, 4, 4) float64 ``T_world_cam``, OpenCV camera axes.
    """
    if not isinstance(n_agents, (int, np.integer)) or not 1 <= n_agents <= MAX_AGENTS:
        raise DataError(f"n_agents must be an integer in 1..{MAX_AGENTS}, got {n_agents!r}")
    s = _check_frames(n_frames)
    rng = np.random.default_rng(seed)
    theta0 = rng.uniform(0, 2 * np.pi)
    jitter = rng.uniform(-0.03, 0.03, size=(n_agents, 2))
    return np.stack([look_at(*_agent(k, theta0, jitter[k])(s)) for k in range(n_agents)])


def make_trajectory(kind: str, n_frames: int, seed: int = 0, size: str | None = None) -> np.ndarray:
    """A camera trajectory of the given kind, identical for identical arguments.

    Kinds: ``orbit`` (arc around the table looking at it), ``walk`` (curving walk with
    look-ahead), ``loop`` (full turn around the table, ends where it started; use
    ``NOMINAL_FRAMES["loop"]`` frames for realistic speed), ``agents`` (agent 0 of
    :func:`make_agent_trajectories` with 2 agents), ``laps`` (two laps around the ``hall``'s
    central block: about 18 m in the ``compact`` hall, 51 m in the ``large`` one; made for
    that scene of the same ``size``, see :data:`TRAJECTORY_SCENES`; use
    :func:`nominal_frames` frames).

    ``size`` applies to ``laps`` only (None = ``compact``); giving it for another kind raises
    :class:`DataError`.

    Returns:
        (n_frames, 4, 4) float64 ``T_world_cam``, OpenCV camera axes.
    """
    if kind not in TRAJECTORY_KINDS:
        raise DataError(f"unknown synthetic trajectory kind {kind!r}; valid: {', '.join(TRAJECTORY_KINDS)}")
    if kind != "laps" and size is not None:
        raise DataError(f"trajectory size {size!r} applies only to kind 'laps', not {kind!r}")
    if kind == "agents":
        return make_agent_trajectories(2, n_frames, seed)[0]
    s = _check_frames(n_frames)
    rng = np.random.default_rng(seed)
    if kind == "laps":
        positions, targets = _laps(s, rng, hall_size(size))
    else:
        positions, targets = {"orbit": _orbit, "walk": _walk, "loop": _loop}[kind](s, rng)
    return look_at(positions, targets)
