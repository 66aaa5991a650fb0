"""The synthetic RGB-D source: procedural rooms rendered along exact trajectories.

The embedded default of the demo and of most tests. A spec string names what to generate::

    synthetic:orbit
    synthetic:walk?frames=200&seed=3&width=320&height=240&noise=1
    synthetic:agents?agent=1&agents=3
    loop                                   (the ``synthetic:`` prefix is optional)

World frame: metres, z up, origin at the floor centre of a 6 x 5 x 3 m room (see
``synthetic_scene``); poses are camera-to-world with OpenCV camera axes. Frames are rendered
lazily by a numpy ray caster (``synthetic_render``), exact unless ``noise=1`` adds Kinect-like
depth noise and holes; ``gt_mesh()`` gives the matching coloured mesh (``synthetic_mesh``).

This module re-exports the pieces so callers need one import.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Iterator
from urllib.parse import parse_qsl

import numpy as np
import trimesh

from slam.data.frame import DataError, Frame
from slam.data.synthetic_mesh import gt_mesh
from slam.data.synthetic_render import (
    DepthNoiseModel,
    RayHits,
    RenderedView,
    add_depth_noise,
    cast_rays,
    default_intrinsics,
    render_rgbd,
    render_view,
)
from slam.data.synthetic_scene import SCENE_KINDS, Scene, make_scene
from slam.data.synthetic_trajectory import (
    NOMINAL_FRAMES,
    TRAJECTORY_KINDS,
    look_at,
    make_agent_trajectories,
    make_trajectory,
)

__all__ = [
    "DepthNoiseModel", "RayHits", "RenderedView", "SCENE_KINDS", "Scene", "SyntheticSequence",
    "SyntheticSpec", "NOMINAL_FRAMES", "TRAJECTORY_KINDS", "add_depth_noise", "cast_rays",
    "default_intrinsics", "gt_mesh", "look_at", "make_agent_trajectories", "make_scene",
    "make_trajectory", "open_synthetic", "parse_synthetic_spec", "render_rgbd", "render_view",
]

SPEC_PREFIX = "synthetic:"
FPS = 30.0
"""Synthetic frames are spaced as a 30 Hz camera: timestamp = original frame number / 30."""
DEFAULT_WIDTH, DEFAULT_HEIGHT = 320, 240
SPEC_OPTIONS = ("frames", "seed", "width", "height", "noise", "agent", "agents")


@dataclass(frozen=True)
class SyntheticSpec:
    """A parsed spec string: what :func:`open_synthetic` generates."""

    kind: str
    frames: int = 100
    seed: int = 0
    width: int = DEFAULT_WIDTH
    height: int = DEFAULT_HEIGHT
    noise: bool = False
    agent: int = 0
    agents: int = 2

    @property
    def name(self) -> str:
        """Canonical spec string (every option spelled out, so equal names mean equal data)."""
        agent = f"&agent={self.agent}&agents={self.agents}" if self.kind == "agents" else ""
        return (f"{SPEC_PREFIX}{self.kind}?frames={self.frames}&seed={self.seed}&width={self.width}"
                f"&height={self.height}&noise={int(self.noise)}{agent}")


class SyntheticSequence:
    """Frames of a synthetic scene along a trajectory; satisfies ``RGBDSequence``.

    Frames are rendered on first access and the most recent ``cache_size`` are kept; every
    access returns fresh array copies.

    Attributes:
        name: the spec string it was made from (or any label).
        scene: the :class:`Scene` rendered.
        trajectory: (N, 4, 4) float64 ``T_world_cam`` of the frames served (after stride/limit).
        K: (3, 3) float64 intrinsics; ``width``, ``height`` the image size.
        frame_numbers: (N,) int original (unstrided) frame numbers; timestamps are these / 30.
    """

    def __init__(self, scene: Scene, trajectory: np.ndarray, K: np.ndarray, width: int, height: int, *,
                 name: str = "synthetic", noise: DepthNoiseModel | None = None, seed: int = 0,
                 frame_numbers: np.ndarray | None = None, cache_size: int = 16) -> None:
        trajectory = np.asarray(trajectory, dtype=np.float64)
        if trajectory.ndim != 3 or trajectory.shape[1:] != (4, 4):
            raise DataError(f"{name}: trajectory must be (N, 4, 4), got {trajectory.shape}")
        self.name = name
        self.scene = scene
        self.trajectory = trajectory
        self.K = np.asarray(K, dtype=np.float64)
        self.width = int(width)
        self.height = int(height)
        self.noise = noise
        self.seed = int(seed)
        self.frame_numbers = np.arange(len(trajectory)) if frame_numbers is None else np.asarray(frame_numbers)
        if self.frame_numbers.shape != (len(trajectory),):
            raise DataError(f"{name}: frame_numbers must be ({len(trajectory)},), got {self.frame_numbers.shape}")
        self._cache: OrderedDict[int, Frame] = OrderedDict()
        self._cache_size = int(cache_size)

    @property
    def has_gt(self) -> bool:
        return True

    def __len__(self) -> int:
        return len(self.trajectory)

    def __getitem__(self, i: int) -> Frame:
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"{self.name}: frame index must be an integer, got {type(i).__name__}")
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"{self.name}: frame {i} out of range for {n} frames")
        i = int(i) % n
        frame = self._cache.get(i)
        if frame is None:
            frame = self._render(i)
            self._cache[i] = frame
            if len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(i)
        # Callers may edit the arrays in place; the cached frame must stay exact.
        return replace(frame, rgb=frame.rgb.copy(), depth=frame.depth.copy(), K=frame.K.copy(),
                       T_world_cam=frame.T_world_cam.copy())

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def _render(self, i: int) -> Frame:
        T = self.trajectory[i]
        view = render_view(self.scene, self.K, T, self.width, self.height)
        depth = view.depth
        number = int(self.frame_numbers[i])
        if self.noise is not None:
            # Seeded by the original frame number: the same frame is equally noisy at any stride.
            rng = np.random.default_rng([self.seed, 0xD0, number])
            depth = add_depth_noise(depth, view.incidence_cos, rng, self.noise)
        return Frame(index=i, timestamp=number / FPS, rgb=view.rgb, depth=depth, K=self.K, T_world_cam=T)

    def gt_mesh(self, spacing: float = 0.1) -> trimesh.Trimesh:
        """The coloured ground-truth mesh of :attr:`scene` (world frame)."""
        return gt_mesh(self.scene, spacing)


def _parse_int(key: str, text: str, spec: str, low: int, high: int | None = None) -> int:
    try:
        value = int(text)
    except ValueError:
        raise DataError(f"synthetic spec {spec!r}: option {key}={text!r} is not an integer") from None
    if value < low or (high is not None and value > high):
        bound = f">= {low}" if high is None else f"in {low}..{high}"
        raise DataError(f"synthetic spec {spec!r}: option {key}={value} must be {bound}")
    return value


def parse_synthetic_spec(spec: str) -> SyntheticSpec:
    """``[synthetic:]KIND[?key=value&...]`` -> :class:`SyntheticSpec`.

    Options: frames (default ``NOMINAL_FRAMES[kind]``: 100, but 500 for ``loop``, whose
    6.3 m path would otherwise move 6 cm and 3.6 deg per frame), seed (0), width (320), height (240, or width * 3 / 4 when
    only width is given), noise (0 or 1), and for ``agents``: agent (0-based, default 0) and
    agents (default 2). Unknown kinds or options raise :class:`DataError` listing the valid ones.
    """
    if not isinstance(spec, str):
        raise DataError(f"synthetic spec must be a string, got {type(spec).__name__}")
    body = spec[len(SPEC_PREFIX):] if spec.startswith(SPEC_PREFIX) else spec
    kind, _, query = body.partition("?")
    if kind not in TRAJECTORY_KINDS:
        raise DataError(f"synthetic spec {spec!r}: unknown kind {kind!r}; valid: {', '.join(TRAJECTORY_KINDS)}")
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError:
        raise DataError(f"synthetic spec {spec!r}: cannot parse options {query!r} (want key=value&...)") from None
    options: dict[str, str] = {}
    for key, value in pairs:
        if key not in SPEC_OPTIONS:
            raise DataError(f"synthetic spec {spec!r}: unknown option {key!r}; valid: {', '.join(SPEC_OPTIONS)}")
        if key in options:
            raise DataError(f"synthetic spec {spec!r}: option {key!r} given twice")
        if key in ("agent", "agents") and kind != "agents":
            raise DataError(f"synthetic spec {spec!r}: option {key!r} applies only to kind 'agents'")
        options[key] = value
    fields: dict[str, object] = {"kind": kind, "frames": NOMINAL_FRAMES[kind]}
    limits = {"frames": (1, None), "seed": (0, 2**63 - 1), "width": (16, 4096), "height": (16, 4096),
              "noise": (0, 1), "agents": (1, 8), "agent": (0, 7)}
    for key, text in options.items():
        fields[key] = _parse_int(key, text, spec, *limits[key])
    if "width" in fields and "height" not in fields:
        fields["height"] = max(16, round(int(fields["width"]) * 3 / 4))  # type: ignore[arg-type]
    fields["noise"] = bool(fields.get("noise", 0))
    parsed = SyntheticSpec(**fields)  # type: ignore[arg-type]
    if parsed.agent >= parsed.agents:
        raise DataError(f"synthetic spec {spec!r}: agent={parsed.agent} must be below agents={parsed.agents}")
    return parsed


def open_synthetic(spec: str, *, width: int | None = None, stride: int = 1, max_frames: int | None = None) -> SyntheticSequence:
    """A lazily rendered synthetic sequence from a spec string (see :func:`parse_synthetic_spec`).

    Args:
        width: override the image width (height keeps the spec's aspect ratio; K is scaled).
        stride: serve every ``stride``-th frame of the path (faster motion, same timestamps).
        max_frames: serve at most this many frames (after striding).
    """
    parsed = parse_synthetic_spec(spec)
    if width is not None:
        if not isinstance(width, (int, np.integer)) or width < 16:
            raise DataError(f"open_synthetic: width must be an integer >= 16, got {width!r}")
        parsed = replace(parsed, width=int(width), height=max(16, round(parsed.height * width / parsed.width)))
    if not isinstance(stride, (int, np.integer)) or stride < 1:
        raise DataError(f"open_synthetic: stride must be a positive integer, got {stride!r}")
    if max_frames is not None and (not isinstance(max_frames, (int, np.integer)) or max_frames < 1):
        raise DataError(f"open_synthetic: max_frames must be a positive integer or None, got {max_frames!r}")
    if parsed.kind == "agents":
        full = make_agent_trajectories(parsed.agents, parsed.frames, parsed.seed)[parsed.agent]
    else:
        full = make_trajectory(parsed.kind, parsed.frames, parsed.seed)
    numbers = np.arange(len(full))[::stride][:max_frames]
    # Agents share one scene: the room depends on the seed only, never on the agent.
    scene = make_scene("room", parsed.seed)
    K = default_intrinsics(parsed.width, parsed.height)
    noise = DepthNoiseModel() if parsed.noise else None
    return SyntheticSequence(scene, full[numbers], K, parsed.width, parsed.height, name=parsed.name,
                             noise=noise, seed=parsed.seed, frame_numbers=numbers)
