"""The synthetic RGB-D source: procedural rooms rendered along exact trajectories.

The embedded default of the demo and of most tests. A spec string names what to generate::

    synthetic:orbit
    synthetic:walk?frames=200&seed=3&width=320&height=240&noise=1
    synthetic:agents?agent=1&agents=3
    synthetic:laps?width=160&height=120&noise=1&blank=300-330
    synthetic:laps?size=large&noise=1
    synthetic:laps?width=160&height=120&exposure=0.3&color_shift=2
    loop                                   (the ``synthetic:`` prefix is optional)

The kind names the trajectory; the scene is the one that trajectory is made for
(``TRAJECTORY_SCENES``): the 6 x 5 x 3 m ``room`` for all but ``laps``, which walks the
``hall`` of its ``size``: ``compact`` (default; 4.4 x 3.6 x 3 m, about 18 m in 780 frames) or
``large`` (10 x 8 x 3 m, about 51 m in 2200 frames). World frame: metres, z up, origin at the floor centre (see
``scene``); poses are camera-to-world with OpenCV camera axes. Frames are rendered
lazily by a numpy ray caster (``render``), exact unless ``noise=1`` adds Kinect-like
depth noise and holes, ``exposure=A`` a per-frame random exposure and white balance and
``color_shift=P`` colour P pixels off its depth (``camera_colour``); ``gt_mesh()`` gives the
matching coloured mesh (``mesh``).

The package: ``scene`` (rooms, halls, primitives and textures), ``trajectory`` (the camera
paths), ``render`` (the ray caster and depth noise), ``mesh`` (the ground-truth mesh); this
module holds the spec parser and the sequence and re-exports the pieces so callers need one
import.
"""

from __future__ import annotations

import re
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Iterator
from urllib.parse import parse_qsl

import numpy as np
import trimesh

from slam.data.frame import DataError, Frame
from slam.data.synthetic.mesh import gt_mesh
from slam.data.synthetic.render import (
    DepthNoiseModel,
    RasterView,
    RayHits,
    add_depth_noise,
    cast_rays,
    default_intrinsics,
    rasterise_view,
    render_rgbd,
)
from slam.data.synthetic.scene import HALL_LAYOUTS, HALL_SIZES, SCENE_KINDS, Scene, make_scene
from slam.data.synthetic.trajectory import (
    LAPS_NOMINAL_FRAMES,
    NOMINAL_FRAMES,
    TRAJECTORY_KINDS,
    TRAJECTORY_SCENES,
    look_at,
    make_agent_trajectories,
    make_trajectory,
    nominal_frames,
)

__all__ = [
    "DepthNoiseModel", "HALL_LAYOUTS", "HALL_SIZES", "LAPS_NOMINAL_FRAMES", "RasterView", "RayHits",
    "SCENE_KINDS", "Scene", "SyntheticSequence", "SyntheticSpec", "NOMINAL_FRAMES", "TRAJECTORY_KINDS",
    "TRAJECTORY_SCENES", "add_depth_noise", "cast_rays", "default_intrinsics", "gt_mesh", "look_at",
    "make_agent_trajectories", "make_scene", "make_trajectory", "nominal_frames", "open_synthetic",
    "parse_synthetic_spec", "rasterise_view", "render_rgbd",
]

SPEC_PREFIX = "synthetic:"
FPS = 30.0
"""Synthetic frames are spaced as a 30 Hz camera: timestamp = original frame number / 30."""
DEFAULT_WIDTH, DEFAULT_HEIGHT = 320, 240
SPEC_OPTIONS = ("frames", "seed", "width", "height", "noise", "agent", "agents", "size", "blank", "drop",
                "exposure", "color_shift")
MAX_EXPOSURE = 0.9
"""Largest ``exposure`` amplitude: gains stay in [0.1, 1.9]."""
MAX_COLOR_SHIFT = 64
"""Largest ``color_shift`` (pixels); it must also stay below a quarter of the width."""

FrameRange = tuple[int, int]
"""Inclusive ``(first, last)`` 0-based frame numbers of the spec's sequence."""


@dataclass(frozen=True)
class SyntheticSpec:
    """A parsed spec string: what :func:`open_synthetic` generates.

    ``blank`` and ``drop`` simulate a tracking loss over an inclusive range of frame numbers
    (0-based indices into the ``frames`` frames of the path, before any stride): ``blank``
    frames stay in the sequence, with their timestamps and GT poses, but their RGB and depth are
    all zero (depth invalid); ``drop`` frames are left out, so the camera jumps and later frames
    keep their timestamps (there is a gap).

    ``size`` is the hall layout of ``laps`` (``compact`` when not given; None for other kinds).

    ``exposure`` (A in [0, 0.9]) and ``color_shift`` (P pixels) imitate a real camera's
    colour (``camera_colour``): a per-frame gain, white balance and bias, and a colour image
    shifted P pixels to the right of its depth. 0: the exact rendered colour.
    """

    kind: str
    frames: int = 100
    seed: int = 0
    width: int = DEFAULT_WIDTH
    height: int = DEFAULT_HEIGHT
    noise: bool = False
    agent: int = 0
    agents: int = 2
    size: str | None = None
    blank: FrameRange | None = None
    drop: FrameRange | None = None
    exposure: float = 0.0
    color_shift: int = 0

    def __post_init__(self) -> None:
        if self.kind == "laps" and self.size is None:
            object.__setattr__(self, "size", HALL_SIZES[0])
        elif self.kind != "laps" and self.size is not None:
            raise DataError(f"SyntheticSpec: size={self.size!r} applies only to kind 'laps', not {self.kind!r}")

    @property
    def name(self) -> str:
        """Canonical spec string (every option spelled out, so equal names mean equal data;
        ``agent``/``agents`` and ``size`` only for the kinds they apply to, ``blank`` and
        ``drop`` only when set)."""
        agent = f"&agent={self.agent}&agents={self.agents}" if self.kind == "agents" else ""
        size = f"&size={self.size}" if self.size is not None else ""
        loss = "".join(f"&{key}={r[0]}-{r[1]}" for key, r in (("blank", self.blank), ("drop", self.drop)) if r is not None)
        camera = (f"&exposure={self.exposure:g}" if self.exposure > 0 else "") + (
            f"&color_shift={self.color_shift}" if self.color_shift > 0 else "")
        return (f"{SPEC_PREFIX}{self.kind}?frames={self.frames}&seed={self.seed}&width={self.width}"
                f"&height={self.height}&noise={int(self.noise)}{agent}{size}{loss}{camera}")


def frame_exposure(seed: int, number: int, amount: float) -> tuple[np.ndarray, np.ndarray]:
    """The exposure of frame ``number``: gain (3,) = g * w with g ~ U[1 - A, 1 + A] and a white
    balance w ~ U[1 - A/5, 1 + A/5] per channel, bias (3,) = b ~ U[-A/5, A/5] on every channel
    (A = ``amount``), seeded by (seed, frame number): the same frame has the same exposure at
    any stride. A = 0: gain 1, bias 0."""
    rng = np.random.default_rng([seed, 0xE7, number])
    g, w, b = rng.uniform(-1, 1), rng.uniform(-1, 1, 3), rng.uniform(-1, 1)
    gain = (1.0 + amount * g) * (1.0 + amount / 5 * w)
    return gain.astype(np.float32), np.full(3, amount / 5 * b, np.float32)


def camera_colour(rgb: np.ndarray, gain: np.ndarray, bias: np.ndarray, shift: int) -> np.ndarray:
    """A camera's view of exact colour rgb (H, W, 3) in [0, 1]: shifted ``shift`` pixels to
    the right against the depth (column x shows what column x - shift sees, the first
    columns repeat column 0), then ``clip(gain * rgb + bias, 0, 1)`` per channel."""
    if shift > 0:
        rgb = np.concatenate([np.repeat(rgb[:, :1], shift, axis=1), rgb[:, :-shift]], axis=1)
    return np.clip(rgb * gain + bias, 0.0, 1.0).astype(np.float32)


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
        blank: inclusive range of frame numbers served blank (all-zero RGB and depth, GT pose
            kept), or None.
        exposure, color_shift: the camera's colour (``camera_colour``; ``exposure_of``).
    """

    def __init__(self, scene: Scene, trajectory: np.ndarray, K: np.ndarray, width: int, height: int, *,
                 name: str = "synthetic", noise: DepthNoiseModel | None = None, seed: int = 0,
                 frame_numbers: np.ndarray | None = None, cache_size: int = 16,
                 blank: FrameRange | None = None, exposure: float = 0.0, color_shift: int = 0) -> None:
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
        self.blank = None if blank is None else (int(blank[0]), int(blank[1]))
        self.exposure = float(exposure)
        self.color_shift = int(color_shift)
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

    def is_blank(self, i: int) -> bool:
        """Whether frame ``i`` (sequence index) is served blank (see ``blank``)."""
        number = int(self.frame_numbers[i])
        return self.blank is not None and self.blank[0] <= number <= self.blank[1]

    def exposure_of(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(gain (3,), bias (3,)) of frame ``i``'s colour (``frame_exposure``)."""
        return frame_exposure(self.seed, int(self.frame_numbers[i]), self.exposure)

    def _render(self, i: int) -> Frame:
        T = self.trajectory[i]
        number = int(self.frame_numbers[i])
        if self.is_blank(i):
            return Frame(index=i, timestamp=number / FPS, rgb=np.zeros((self.height, self.width, 3), np.float32),
                         depth=np.zeros((self.height, self.width), np.float32), K=self.K, T_world_cam=T)
        view = rasterise_view(self.scene, self.K, T, self.width, self.height)
        depth = view.depth
        if self.noise is not None:
            # Seeded by the original frame number: the same frame is equally noisy at any stride.
            rng = np.random.default_rng([self.seed, 0xD0, number])
            depth = add_depth_noise(depth, view.incidence_cos, rng, self.noise)
        rgb = view.rgb
        if self.exposure > 0 or self.color_shift > 0:
            rgb = camera_colour(rgb, *self.exposure_of(i), self.color_shift)
        return Frame(index=i, timestamp=number / FPS, rgb=rgb, depth=depth, K=self.K, T_world_cam=T)

    def gt_mesh(self, spacing: float = 0.1) -> trimesh.Trimesh:
        """The coloured ground-truth mesh of :attr:`scene` (world frame)."""
        return gt_mesh(self.scene, spacing)


MAX_FRAMES = 20_000
"""Most frames a synthetic spec may ask for (the large laps hall's nominal path is 2,200): the
trajectory and its ground truth are made for every frame, so the count bounds the work."""
MAX_SIDE = 2048
"""Largest synthetic image side (pixels)."""


def _parse_int(key: str, text: str, spec: str, low: int, high: int | None = None) -> int:
    try:
        value = int(text)
    except ValueError:
        raise DataError(f"synthetic spec {spec!r}: option {key}={text!r} is not an integer") from None
    if value < low or (high is not None and value > high):
        bound = f">= {low}" if high is None else f"in {low}..{high}"
        raise DataError(f"synthetic spec {spec!r}: option {key}={value} must be {bound}")
    return value


def _parse_float(key: str, text: str, spec: str, low: float, high: float) -> float:
    try:
        value = float(text)
    except ValueError:
        raise DataError(f"synthetic spec {spec!r}: option {key}={text!r} is not a number") from None
    if not low <= value <= high:  # NaN fails too
        raise DataError(f"synthetic spec {spec!r}: option {key}={text} must be in [{low:g}, {high:g}]")
    return value


def _parse_range(key: str, text: str, spec: str, frames: int) -> FrameRange:
    """``A-B`` -> (A, B), 0 <= A <= B < frames."""
    match = re.fullmatch(r"([0-9]+)-([0-9]+)", text)
    if match is None:
        raise DataError(f"synthetic spec {spec!r}: option {key}={text!r} must be a frame range A-B "
                        f"(inclusive, 0-based, e.g. {key}=100-130)")
    a, b = int(match[1]), int(match[2])
    if a > b:
        raise DataError(f"synthetic spec {spec!r}: option {key}={text}: the range is reversed (first {a} > last {b})")
    if b >= frames:
        raise DataError(f"synthetic spec {spec!r}: option {key}={text}: frame {b} is beyond the last frame "
                        f"{frames - 1} (frames={frames})")
    return a, b


def parse_synthetic_spec(spec: str) -> SyntheticSpec:
    """``[synthetic:]KIND[?key=value&...]`` -> :class:`SyntheticSpec`.

    Options: frames (default :func:`nominal_frames`: 100, but 500 for ``loop``, whose
    6.3 m path would otherwise move 6 cm and 3.6 deg per frame, and for ``laps`` 780 in the
    compact hall (18 m) or 2200 in the large one (51 m)), seed (0), width (320), height (240,
    or width * 3 / 4 when only width is given), noise (0 or 1), for ``agents``: agent (0-based,
    default 0) and agents (default 2), for ``laps``: size (``compact``, the default, or
    ``large``; see ``HALL_LAYOUTS``), and a forced tracking loss: blank=A-B (frames A..B served
    all black with no depth) and drop=A-B (frames A..B left out); see :class:`SyntheticSpec`;
    the camera's colour: exposure=A (a number in [0, 0.9]) and color_shift=P (pixels, 0..64 and
    below width / 4).
    Unknown kinds or options raise :class:`DataError` listing the valid ones.
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
        if key == "size" and kind != "laps":
            raise DataError(f"synthetic spec {spec!r}: option 'size' applies only to kind 'laps'")
        options[key] = value
    size = None
    if kind == "laps":
        size = options.get("size", HALL_SIZES[0])
        if size not in HALL_SIZES:
            raise DataError(f"synthetic spec {spec!r}: option size={size!r} must be one of {', '.join(HALL_SIZES)}")
    fields: dict[str, object] = {"kind": kind, "frames": nominal_frames(kind, size), "size": size}
    limits = {"frames": (1, MAX_FRAMES), "seed": (0, 2**63 - 1), "width": (16, MAX_SIDE), "height": (16, MAX_SIDE),
              "noise": (0, 1), "agents": (1, 8), "agent": (0, 7)}
    limits["color_shift"] = (0, MAX_COLOR_SHIFT)
    for key, text in options.items():
        if key not in ("blank", "drop", "size", "exposure"):
            fields[key] = _parse_int(key, text, spec, *limits[key])
    if "exposure" in options:
        fields["exposure"] = _parse_float("exposure", options["exposure"], spec, 0.0, MAX_EXPOSURE)
    for key in ("blank", "drop"):
        if key in options:
            fields[key] = _parse_range(key, options[key], spec, int(fields["frames"]))  # type: ignore[arg-type]
    if fields.get("drop") == (0, int(fields["frames"]) - 1):  # type: ignore[arg-type]
        raise DataError(f"synthetic spec {spec!r}: option drop={options['drop']} leaves no frames")
    if "width" in fields and "height" not in fields:
        fields["height"] = max(16, round(int(fields["width"]) * 3 / 4))  # type: ignore[arg-type]
    fields["noise"] = bool(fields.get("noise", 0))
    width = int(fields.get("width", DEFAULT_WIDTH))  # type: ignore[arg-type]
    if 4 * int(fields.get("color_shift", 0)) >= width:  # type: ignore[arg-type]
        raise DataError(f"synthetic spec {spec!r}: option color_shift={fields['color_shift']} must be below "
                        f"a quarter of the width ({width})")
    parsed = SyntheticSpec(**fields)  # type: ignore[arg-type]
    if parsed.agent >= parsed.agents:
        raise DataError(f"synthetic spec {spec!r}: agent={parsed.agent} must be below agents={parsed.agents}")
    return parsed


def open_synthetic(spec: str, *, width: int | None = None, stride: int = 1, max_frames: int | None = None) -> SyntheticSequence:
    """A lazily rendered synthetic sequence from a spec string (see :func:`parse_synthetic_spec`).

    Args:
        width: override the image width (height keeps the spec's aspect ratio; K is scaled).
        stride: serve every ``stride``-th frame of the path (faster motion, same timestamps).
        max_frames: serve at most this many frames (after striding and the spec's ``drop``).
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
        full = make_trajectory(parsed.kind, parsed.frames, parsed.seed, size=parsed.size)
    numbers = np.arange(len(full))[::stride]
    if parsed.drop is not None:
        numbers = numbers[(numbers < parsed.drop[0]) | (numbers > parsed.drop[1])]
        if len(numbers) == 0:
            raise DataError(f"open_synthetic: {parsed.name} with stride={stride} leaves no frames")
    numbers = numbers[:max_frames]
    # Agents share one scene: the room depends on the seed only, never on the agent.
    scene = make_scene(TRAJECTORY_SCENES[parsed.kind], parsed.seed, size=parsed.size)
    K = default_intrinsics(parsed.width, parsed.height)
    noise = DepthNoiseModel() if parsed.noise else None
    return SyntheticSequence(scene, full[numbers], K, parsed.width, parsed.height, name=parsed.name,
                             noise=noise, seed=parsed.seed, frame_numbers=numbers, blank=parsed.blank,
                             exposure=parsed.exposure, color_shift=parsed.color_shift)
