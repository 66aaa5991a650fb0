"""Camera trajectories through the synthetic room (world frame of ``synthetic_scene``: z up).

Every kind is a fixed smooth path ``p(s)`` with a look-at target ``q(s)`` for ``s`` in [0, 1];
``n_frames`` only sets how finely it is sampled, so more frames mean smaller steps. At
:data:`NOMINAL_FRAMES` each kind moves at most ~1.5 cm and ~1 degree per frame (handheld
motion at 30 Hz). The seed jitters radius, height, start angle, direction and mirroring.

All paths stay in the free ring around the central table: horizontally at least 1 m from every
wall (furniture occupies only the 0.55 m band along them) and at least 0.45 m from the table's
footprint, at heights 1.3-1.6 m, looking at content 0.5-5 m away.

Poses are camera-to-world with OpenCV camera axes: x right, y down, z forward.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from slam.data.frame import DataError

TRAJECTORY_KINDS = ("orbit", "walk", "loop", "agents")
NOMINAL_FRAMES = {"orbit": 100, "walk": 100, "loop": 500, "agents": 100}
"""Frame count at which each kind moves <= ~1.5 cm and ~1 deg per frame."""
TABLE_TARGET = np.array([0.0, 0.0, 0.85])
"""Where inward-looking paths aim: just above the table top at the room centre."""
MAX_AGENTS = 8
WORLD_UP = (0.0, 0.0, 1.0)


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


def make_trajectory(kind: str, n_frames: int, seed: int = 0) -> np.ndarray:
    """A camera trajectory of the given kind, identical for identical arguments.

    Kinds: ``orbit`` (arc around the table looking at it), ``walk`` (curving walk with
    look-ahead), ``loop`` (full turn around the table, ends where it started; use
    ``NOMINAL_FRAMES["loop"]`` frames for realistic speed), ``agents`` (agent 0 of
    :func:`make_agent_trajectories` with 2 agents).

    Returns:
        (n_frames, 4, 4) float64 ``T_world_cam``, OpenCV camera axes.
    """
    if kind not in TRAJECTORY_KINDS:
        raise DataError(f"unknown synthetic trajectory kind {kind!r}; valid: {', '.join(TRAJECTORY_KINDS)}")
    if kind == "agents":
        return make_agent_trajectories(2, n_frames, seed)[0]
    s = _check_frames(n_frames)
    path = {"orbit": _orbit, "walk": _walk, "loop": _loop}[kind]
    positions, targets = path(s, np.random.default_rng(seed))
    return look_at(positions, targets)
