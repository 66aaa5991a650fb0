"""Procedural indoor scenes for the synthetic RGB-D source: analytic primitives and textures.

World frame (used by the whole synthetic source): metres, **z up**, origin at the centre of the
floor. The default room spans x in [-3, 3], y in [-2.5, 2.5], z in [0, 3]. Furniture stays in a
band within :data:`WALL_BAND` metres of the walls plus one table at the room centre (its footprint
inside :data:`TABLE_MAX_HALF_SIZE`), which leaves a free ring around the table where the synthetic
trajectories move (see ``trajectory.py``).

The ``hall`` kind is a ring corridor around a solid full-height central block, for
loop-closure benchmarks, in two sizes (:data:`HALL_LAYOUTS`): ``compact`` (the default), 4.4 x 3.6
x 3 m around a 1.6 x 0.8 m block, corridors 1.4 m wide, and ``large``, 10 x 8 x 3 m around a
5.6 x 3.6 m block, corridors 2.2 m wide. Each holds one cabinet-and-picture set at several places
(``repeat_spots``, rendered identically), plain single-colour stretches and otherwise distinct
textures per wall; furniture stays within ``wall_band`` of its wall (see :func:`make_scene`).

Colour is a function of the 3D surface point and its normal only (a texture times a fixed
directional "half-Lambert" shading), so every view of a point sees the same colour and the GT
mesh's vertex colours match the renders. Texture features are at least :data:`MIN_FEATURE_SIZE`
metres so that 320x240 frames do not alias badly.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Literal, Union

import numpy as np

from slam.data.frame import DataError

Vec3 = tuple[float, float, float]
RGB = tuple[float, float, float]

MIN_FEATURE_SIZE = 0.03
"""Smallest texture period/cell allowed, metres."""
WALL_BAND = 0.55
"""Wall furniture stays within this distance of its wall, metres."""
TABLE_MAX_HALF_SIZE = (0.56, 0.40)
"""Largest half extents (x, y) of the central table's top, metres, before its small yaw."""
TABLE_OBJECT_MAX_HEIGHT = 0.25
"""Objects on the table rise at most this far above its top, metres."""

Pattern = Literal["solid", "checker", "stripes", "noise", "wood"]
PATTERNS: tuple[str, ...] = ("solid", "checker", "stripes", "noise", "wood")


@dataclass(frozen=True)
class Texture:
    """A procedural albedo: a pattern value in [0, 1] blends ``colour_a`` into ``colour_b``.

    Patterns (``scale`` is in metres):
        solid: ``colour_a`` everywhere (only the grain varies it).
        checker: squares of side ``scale`` on the plane facing the normal's dominant axis
            (triplanar), edges softened over ~scale/6.
        stripes: soft bands of period ``scale`` across ``direction``.
        noise: smooth value-noise blobs of size ~``scale`` (2 octaves).
        wood: rings of spacing ``scale`` around an axis along ``direction``, bent by noise.
    Except on ``noise`` patterns, a low-frequency brightness grain of relative amplitude
    ``grain`` (blobs of 0.6 m) is applied on top, so no large surface is perfectly uniform.
    """

    pattern: Pattern
    colour_a: RGB
    colour_b: RGB = (0.0, 0.0, 0.0)
    scale: float = 0.2
    direction: Vec3 = (1.0, 0.0, 0.0)
    seed: int = 0
    grain: float = 0.12

    def __post_init__(self) -> None:
        if self.pattern not in PATTERNS:
            raise ValueError(f"Texture.pattern {self.pattern!r} is not one of {PATTERNS}")
        if self.scale < MIN_FEATURE_SIZE:
            raise ValueError(f"Texture.scale {self.scale} m is below {MIN_FEATURE_SIZE} m (aliases)")
        for name in ("colour_a", "colour_b"):
            colour = getattr(self, name)
            if len(colour) != 3 or min(colour) < 0 or max(colour) > 1:
                raise ValueError(f"Texture.{name} {colour} must be three values in [0, 1]")
        if np.linalg.norm(self.direction) < 1e-9:
            raise ValueError("Texture.direction must be non-zero")


@dataclass(frozen=True)
class Room:
    """An axis-aligned box seen from inside: floor, ceiling and four walls.

    ``textures`` are per face, ordered by :data:`ROOM_FACES`: face ``2 * axis + side`` lies at
    ``lo[axis]`` (side 0) or ``hi[axis]`` (side 1); its normal points into the room.
    """

    lo: Vec3
    hi: Vec3
    textures: tuple[Texture, Texture, Texture, Texture, Texture, Texture]

    def __post_init__(self) -> None:
        if not all(h - l > 0.5 for l, h in zip(self.lo, self.hi)):
            raise ValueError(f"Room lo {self.lo} / hi {self.hi}: every extent must exceed 0.5 m")
        if len(self.textures) != 6:
            raise ValueError(f"Room needs 6 face textures, got {len(self.textures)}")


ROOM_FACES = ("wall_x_lo", "wall_x_hi", "wall_y_lo", "wall_y_hi", "floor", "ceiling")


@dataclass(frozen=True)
class Box:
    """A box with half extents ``half_size`` about ``centre``, turned by ``yaw`` (rad) about +z.

    ``mesh_bottom=False`` leaves the bottom face out of :func:`gt_mesh` where the box rests on a
    support and that face can never be seen (the ray caster never reaches it either).
    """

    centre: Vec3
    half_size: Vec3
    texture: Texture
    yaw: float = 0.0
    mesh_bottom: bool = True

    def __post_init__(self) -> None:
        if min(self.half_size) <= 0:
            raise ValueError(f"Box.half_size {self.half_size} must be positive")

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) float64 box-to-world rotation."""
        return yaw_matrix(self.yaw)


@dataclass(frozen=True)
class Sphere:
    centre: Vec3
    radius: float
    texture: Texture

    def __post_init__(self) -> None:
        if self.radius <= 0:
            raise ValueError(f"Sphere.radius {self.radius} must be positive")


@dataclass(frozen=True)
class Cylinder:
    """A vertical (z-axis) solid cylinder from ``base`` (x, y, z of the bottom centre) up ``height``."""

    base: Vec3
    radius: float
    height: float
    texture: Texture
    mesh_bottom: bool = True

    def __post_init__(self) -> None:
        if self.radius <= 0 or self.height <= 0:
            raise ValueError(f"Cylinder radius {self.radius} / height {self.height} must be positive")


@dataclass(frozen=True)
class Table:
    """A table: a top slab on four square legs, turned by ``yaw`` about the vertical through ``centre``.

    ``centre`` is (x, y) on the floor; ``top_half_size`` the (x, y) half extents of the top;
    ``height`` the height of the top surface.
    """

    centre: tuple[float, float]
    top_half_size: tuple[float, float]
    height: float
    top_texture: Texture
    leg_texture: Texture
    yaw: float = 0.0
    top_thickness: float = 0.04
    leg_half_width: float = 0.03
    leg_inset: float = 0.05

    def parts(self) -> tuple[Box, ...]:
        """The top and four legs as boxes (legs are not drawn on their floor contact)."""
        R = yaw_matrix(self.yaw)
        cx, cy = self.centre
        hx, hy = self.top_half_size
        t = self.top_thickness
        top = Box((cx, cy, self.height - t / 2), (hx, hy, t / 2), self.top_texture, self.yaw)
        leg_h = (self.height - t) / 2
        legs = []
        for sx in (-1, 1):
            for sy in (-1, 1):
                local = np.array([sx * (hx - self.leg_inset), sy * (hy - self.leg_inset), 0.0])
                x, y, _ = R @ local
                legs.append(
                    Box(
                        (cx + x, cy + y, leg_h),
                        (self.leg_half_width, self.leg_half_width, leg_h),
                        self.leg_texture,
                        self.yaw,
                        mesh_bottom=False,
                    )
                )
        return (top, *legs)

    @property
    def top_z(self) -> float:
        return self.height


Primitive = Union[Box, Sphere, Cylinder]


@dataclass(frozen=True)
class Scene:
    """A room, the objects in it and the light that shades them.

    ``light_direction`` points from surfaces towards the (directional) light, world frame.
    """

    room: Room
    objects: tuple[Union[Primitive, Table], ...]
    light_direction: Vec3 = (0.35, 0.25, 0.9)
    name: str = "room"
    groups: tuple[tuple[str, tuple[int, ...]], ...] = ()
    """Named sets of surface ids (:meth:`surface_textures` order) that benchmarks can look for in
    rendered ``surface`` images, e.g. the ``hall``'s repeated furniture; empty for ``room``."""

    def group(self, name: str) -> tuple[int, ...]:
        """Surface ids of the group called ``name`` (KeyError listing the names if absent)."""
        for key, ids in self.groups:
            if key == name:
                return ids
        raise KeyError(f"scene {self.name!r} has no surface group {name!r}; groups: {[k for k, _ in self.groups]}")

    @property
    def primitives(self) -> tuple[Primitive, ...]:
        """Objects with tables expanded into their boxes, in a fixed order (surface ids follow it)."""
        flat: list[Primitive] = []
        for obj in self.objects:
            flat.extend(obj.parts() if isinstance(obj, Table) else (obj,))
        return tuple(flat)

    def surface_textures(self) -> tuple[Texture, ...]:
        """Texture of every surface id: the 6 room faces, then one per primitive."""
        return (*self.room.textures, *(p.texture for p in self.primitives))


def yaw_matrix(yaw: float) -> np.ndarray:
    """(3, 3) float64 rotation by ``yaw`` radians about +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------
# Textures: pure functions of (points, normals).


@lru_cache(maxsize=256)
def _noise_table(seed: int) -> np.ndarray:
    """(65536,) float32 uniform [0, 1) lattice values for one noise seed."""
    table = np.random.default_rng([seed, 0x5EED]).random(1 << 16, dtype=np.float32)
    table.setflags(write=False)
    return table


_HASH_PRIMES = (np.int32(73856093), np.int32(19349663), np.int32(83492791))


def _lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a + t * (b - a)


def value_noise(points: np.ndarray, seed: int) -> np.ndarray:
    """(3, N) points in lattice units -> (N,) float32 smooth noise in [0, 1].

    Random values at integer lattice corners (a multiply-xor spatial hash of the corner into a
    16-bit table of uniform values; int32 products wrap on purpose), blended trilinearly with
    smoothstep weights ``w = f^2 (3 - 2 f)`` so the field is C1 (no creases that look like edges).
    """
    table = _noise_table(seed)
    cell = np.floor(points)
    f = (points - cell).astype(np.float32)
    wx, wy, wz = f * f * (3.0 - 2.0 * f)
    i = cell.astype(np.int32)
    hx0, hy0, hz0 = (i[k] * _HASH_PRIMES[k] for k in range(3))
    hx1, hy1, hz1 = (h + p for h, p in zip((hx0, hy0, hz0), _HASH_PRIMES))

    def corner(hx: np.ndarray, hy: np.ndarray, hz: np.ndarray) -> np.ndarray:
        return table[(hx ^ hy ^ hz) & 0xFFFF]

    y0z0 = _lerp(corner(hx0, hy0, hz0), corner(hx1, hy0, hz0), wx)
    y1z0 = _lerp(corner(hx0, hy1, hz0), corner(hx1, hy1, hz0), wx)
    y0z1 = _lerp(corner(hx0, hy0, hz1), corner(hx1, hy0, hz1), wx)
    y1z1 = _lerp(corner(hx0, hy1, hz1), corner(hx1, hy1, hz1), wx)
    return _lerp(_lerp(y0z0, y1z0, wy), _lerp(y0z1, y1z1, wy), wz)


def fractal_noise(points: np.ndarray, seed: int, octaves: int = 2) -> np.ndarray:
    """(3, N) points in lattice units -> (N,) float32 sum of value-noise octaves, in [0, 1]."""
    total = np.zeros(points.shape[1], dtype=np.float32)
    norm = 0.0
    for octave in range(octaves):
        amplitude = 0.5**octave
        total += amplitude * value_noise(points * 2.0**octave, seed + 101 * octave)
        norm += amplitude
    return total / np.float32(norm)


def _soft_square(phase: np.ndarray, sharpness: float = 4.0) -> np.ndarray:
    """Smoothed square wave of ``sin(phase)`` in [-1, 1]: flat plateaus, edges ~1/sharpness wide."""
    return np.tanh(sharpness * np.sin(phase))


@lru_cache(maxsize=1024)
def _pattern_offset(seed: int) -> np.ndarray:
    """(3, 1) fixed pseudo-random offset (lattice units) so patterns of different seeds differ
    and no wall sits exactly on a checker/noise lattice plane."""
    offset = (np.random.default_rng(seed + 7).uniform(0.13, 0.87, size=3) + 17.0 * (seed % 5))[:, None]
    offset.setflags(write=False)
    return offset


def pattern_value(texture: Texture, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Pattern of ``texture`` at (3, N) world points with (3, N) unit normals -> (N,) float32 in [0, 1]."""
    if texture.pattern == "solid":
        return np.zeros(points.shape[1], dtype=np.float32)
    q = points / texture.scale + _pattern_offset(texture.seed)
    if texture.pattern == "checker":
        # Triplanar: the two coordinates orthogonal to the dominant normal axis.
        axis = np.abs(normals).argmax(axis=0)
        columns = np.arange(points.shape[1])
        u = q[(axis + 1) % 3, columns].astype(np.float32)
        v = q[(axis + 2) % 3, columns].astype(np.float32)
        return 0.5 + 0.5 * np.tanh(4.0 * np.sin(np.float32(np.pi) * u) * np.sin(np.float32(np.pi) * v))
    direction = np.asarray(texture.direction, dtype=np.float64)
    direction = direction / np.linalg.norm(direction)
    along = direction @ q
    if texture.pattern == "stripes":
        return 0.5 + 0.5 * _soft_square((2 * np.pi * along).astype(np.float32))
    if texture.pattern == "noise":
        n = fractal_noise(q, texture.seed, octaves=2)
        # Stretch contrast: raw value noise clusters around 0.5.
        return np.clip((n - 0.5) * 2.2 + 0.5, 0.0, 1.0)
    # wood: distance to an axis along `direction`, bent by noise so rings wobble.
    across = q - along * direction[:, None]
    radial = np.sqrt(across[0] ** 2 + across[1] ** 2 + across[2] ** 2)
    bend = fractal_noise(q * 0.5, texture.seed + 3, octaves=1)
    return 0.5 + 0.5 * _soft_square((2 * np.pi * (radial + 1.5 * bend)).astype(np.float32), sharpness=2.0)


def texture_albedo(texture: Texture, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(3, N) world points, (3, N) unit normals -> (3, N) float32 albedo in [0, 1]."""
    value = pattern_value(texture, points, normals)
    a = np.asarray(texture.colour_a, dtype=np.float32)[:, None]
    b = np.asarray(texture.colour_b, dtype=np.float32)[:, None]
    albedo = a + value * (b - a)
    if texture.grain > 0 and texture.pattern != "noise":  # noise patterns vary enough already
        grain = value_noise(points / 0.6 + 0.37, texture.seed + 999)
        albedo = albedo * (1.0 + np.float32(texture.grain) * (2.0 * grain - 1.0))
    return np.clip(albedo, 0.0, 1.0)


def shading(normals: np.ndarray, light_direction: Vec3) -> np.ndarray:
    """(3, N) unit normals -> (N,) float32 view-independent brightness in [0.45, 1] (half-Lambert)."""
    light = np.asarray(light_direction, dtype=np.float64)
    light = light / np.linalg.norm(light)
    return (0.45 + 0.55 * (0.5 + 0.5 * (light @ normals))).astype(np.float32)


def group_indices(ids: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """(N,) small ints -> [(value, (M,) indices where ids == value)] for each value present.

    One stable sort (a radix sort on int16) instead of a full-array comparison per value.
    """
    if len(ids) == 0:
        return []
    low, high = int(ids.min()), int(ids.max())
    if low < -(2**15) or high >= 2**15:
        raise ValueError(f"group_indices: ids must fit in int16, got {low}..{high}")
    order = np.argsort(ids.astype(np.int16), kind="stable")
    counts = np.bincount(ids - low)
    ends = np.cumsum(counts)
    return [(low + int(v), order[ends[v] - counts[v]:ends[v]]) for v in np.flatnonzero(counts)]


def surface_colour(scene: Scene, surface_ids: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Shaded colour of scene surfaces (component-major arrays).

    Args:
        surface_ids: (N,) int surface index (see :meth:`Scene.surface_textures`); -1 = none (black).
        points: (3, N) world points on those surfaces.
        normals: (3, N) unit normals there (pointing to the visible side).
    Returns:
        (3, N) float32 RGB in [0, 1].
    """
    textures = scene.surface_textures()
    colour = np.zeros((3, points.shape[1]), dtype=np.float32)
    for sid, sel in group_indices(surface_ids):
        if sid >= 0:
            colour[:, sel] = texture_albedo(textures[sid], points[:, sel], normals[:, sel])
    return np.clip(colour * shading(normals, scene.light_direction), 0.0, 1.0)


# ----------------------------------------------------------------------------------------------
# Procedural scene generation.

_PALETTE: tuple[RGB, ...] = (
    (0.85, 0.33, 0.22), (0.93, 0.70, 0.25), (0.30, 0.55, 0.80), (0.25, 0.65, 0.40),
    (0.60, 0.35, 0.70), (0.90, 0.88, 0.80), (0.20, 0.22, 0.28), (0.55, 0.40, 0.25),
    (0.75, 0.80, 0.35), (0.30, 0.75, 0.75), (0.85, 0.50, 0.60), (0.45, 0.45, 0.50),
)
SCENE_KINDS = ("room", "empty", "hall")


def _pair(rng: np.random.Generator) -> tuple[RGB, RGB]:
    """Two clearly different palette colours (contrast matters for photometric tracking)."""
    i, j = rng.choice(len(_PALETTE), size=2, replace=False)
    return _PALETTE[i], _PALETTE[j]


def _random_texture(rng: np.random.Generator, *, scale_range: tuple[float, float], patterns: tuple[str, ...]) -> Texture:
    a, b = _pair(rng)
    direction = rng.normal(size=3)
    return Texture(
        pattern=str(rng.choice(patterns)),  # type: ignore[arg-type]
        colour_a=a,
        colour_b=b,
        scale=float(rng.uniform(*scale_range)),
        direction=tuple(float(x) for x in direction / np.linalg.norm(direction)),
        seed=int(rng.integers(0, 2**31 - 1)),
    )


def _room(rng: np.random.Generator) -> Room:
    """6 x 5 x 3 m room, each face with its own texture and colours."""
    def wall(direction: Vec3) -> Texture:
        pattern = str(rng.choice(("noise", "stripes", "checker", "wood")))
        a, b = _pair(rng)
        return Texture(pattern, a, b, scale=float(rng.uniform(0.22, 0.45)), direction=direction,  # type: ignore[arg-type]
                       seed=int(rng.integers(0, 2**31 - 1)))

    # Stripes/wood on a wall need a direction lying in the wall: vertical or horizontal.
    walls = [wall((0.0, 0.0, 1.0) if rng.random() < 0.5 else d) for d in ((0, 1, 0), (0, 1, 0), (1, 0, 0), (1, 0, 0))]
    floor_a, floor_b = _pair(rng)
    floor = Texture(str(rng.choice(("wood", "checker"))), floor_a, floor_b,  # type: ignore[arg-type]
                    scale=float(rng.uniform(0.25, 0.4)), direction=(1.0, 0.0, 0.0) if rng.random() < 0.5 else (0.0, 1.0, 0.0),
                    seed=int(rng.integers(0, 2**31 - 1)))
    ceiling = Texture("noise", (0.92, 0.92, 0.88), (0.70, 0.72, 0.78), scale=0.5, seed=int(rng.integers(0, 2**31 - 1)))
    return Room((-3.0, -2.5, 0.0), (3.0, 2.5, 3.0), (walls[0], walls[1], walls[2], walls[3], floor, ceiling))


def _table_with_objects(rng: np.random.Generator) -> list[Union[Primitive, Table]]:
    """The central table and 3 objects on it, kept inside its top and below the height limit."""
    hx = float(rng.uniform(0.46, TABLE_MAX_HALF_SIZE[0]))
    hy = float(rng.uniform(0.32, TABLE_MAX_HALF_SIZE[1]))
    yaw = float(rng.uniform(-0.2, 0.2))
    centre = (float(rng.uniform(-0.05, 0.05)), float(rng.uniform(-0.05, 0.05)))
    table = Table(
        centre, (hx, hy), float(rng.uniform(0.72, 0.78)),
        top_texture=_random_texture(rng, scale_range=(0.08, 0.15), patterns=("wood", "checker", "noise")),
        leg_texture=_random_texture(rng, scale_range=(0.05, 0.08), patterns=("solid", "stripes")),
        yaw=yaw,
    )
    R = yaw_matrix(yaw)
    top = table.top_z
    objects: list[Union[Primitive, Table]] = [table]
    kinds = rng.permutation(["box", "sphere", "cylinder"])
    for slot, kind in zip((-1.0, 0.0, 1.0), kinds):
        # Slots along the long axis, >= 0.25 m apart; footprints (<= 0.12 m from their centre)
        # stay inside the top's edge and never touch each other.
        local = np.array([slot * (hx - 0.17) + rng.uniform(-0.02, 0.02), rng.uniform(-0.5, 0.5) * (hy - 0.2), 0.0])
        x, y = (np.array(centre) + (R @ local)[:2]).tolist()
        texture = _random_texture(rng, scale_range=(0.03, 0.06), patterns=("checker", "stripes", "noise"))
        if kind == "box":
            half = (float(rng.uniform(0.05, 0.08)), float(rng.uniform(0.05, 0.08)), float(rng.uniform(0.05, TABLE_OBJECT_MAX_HEIGHT / 2)))
            objects.append(Box((x, y, top + half[2]), half, texture, yaw=float(rng.uniform(0, np.pi / 2)), mesh_bottom=False))
        elif kind == "sphere":
            r = float(rng.uniform(0.06, 0.09))
            objects.append(Sphere((x, y, top + r), r, texture))
        else:
            objects.append(Cylinder((x, y, top), float(rng.uniform(0.05, 0.08)),
                                    float(rng.uniform(0.1, TABLE_OBJECT_MAX_HEIGHT)), texture, mesh_bottom=False))
    return objects


def _wall_furniture(rng: np.random.Generator, room: Room) -> list[Primitive]:
    """Cabinets, a shelf, pictures, a pot and a ball in the band along the walls.

    Positions are drawn per wall segment so that pieces never overlap one another.
    """
    (x0, y0, _), (x1, y1, _) = room.lo, room.hi
    tex = lambda: _random_texture(rng, scale_range=(0.06, 0.2), patterns=("checker", "stripes", "noise", "wood"))  # noqa: E731
    out: list[Primitive] = []
    # Wall y = hi: a low cabinet in the left half, a picture in the right half.
    w, d, h = rng.uniform(0.35, 0.6), rng.uniform(0.2, 0.25), rng.uniform(0.35, 0.5)
    out.append(Box((float(rng.uniform(-1.6, -0.6)), y1 - d, h), (w, d, h), tex(), mesh_bottom=False))
    out.append(Box((float(rng.uniform(0.6, 1.8)), y1 - 0.02, float(rng.uniform(1.3, 1.7))),
                   (float(rng.uniform(0.3, 0.5)), 0.02, float(rng.uniform(0.2, 0.3))), tex()))
    # Wall x = lo: a tall shelf.
    w, d, h = rng.uniform(0.4, 0.6), rng.uniform(0.2, 0.25), rng.uniform(0.8, 1.0)
    out.append(Box((x0 + d, float(rng.uniform(-1.0, 1.0)), h), (d, w, h), tex(), mesh_bottom=False))
    # Wall y = lo: a crate turned a little (its corners stay in the band) and a picture.
    w, d, h = rng.uniform(0.25, 0.35), rng.uniform(0.18, 0.22), rng.uniform(0.2, 0.3)
    yaw = float(rng.uniform(-0.15, 0.15))
    out.append(Box((float(rng.uniform(0.5, 1.6)), y0 + 0.29, h), (w, d, h), tex(), yaw=yaw, mesh_bottom=False))
    out.append(Box((float(rng.uniform(-1.8, -0.5)), y0 + 0.02, float(rng.uniform(1.3, 1.7))),
                   (float(rng.uniform(0.3, 0.5)), 0.02, float(rng.uniform(0.2, 0.3))), tex()))
    # Wall x = hi: a cabinet and a picture above it.
    w, d, h = rng.uniform(0.4, 0.7), rng.uniform(0.2, 0.25), rng.uniform(0.4, 0.55)
    yc = float(rng.uniform(-0.8, 0.8))
    out.append(Box((x1 - d, yc, h), (d, w, h), tex(), mesh_bottom=False))
    out.append(Box((x1 - 0.02, yc + float(rng.uniform(-0.3, 0.3)), float(rng.uniform(1.5, 1.9))),
                   (0.02, float(rng.uniform(0.3, 0.45)), float(rng.uniform(0.2, 0.3))), tex()))
    # A plant pot in one corner, a ball in the opposite one.
    sx, sy = rng.choice([-1, 1], size=2)
    r = float(rng.uniform(0.15, 0.22))
    out.append(Cylinder((sx * (x1 - 0.3), sy * (y1 - 0.3), 0.0), r, float(rng.uniform(0.4, 0.8)), tex(), mesh_bottom=False))
    r = float(rng.uniform(0.15, 0.22))
    out.append(Sphere((-sx * (x1 - 0.3), -sy * (y1 - 0.3), r), r, tex()))
    return out


def make_scene(kind: str = "room", seed: int = 0, size: str | None = None) -> Scene:
    """A procedural indoor scene, identical for identical ``(kind, seed, size)``.

    Kinds:
        room: 6 x 5 x 3 m room (textured floor, ceiling, 4 walls), a central table with 3 objects
            on it, and 9 pieces along the walls (cabinets, shelf, crate, pictures, pot, ball).
        empty: the textured room only.
        hall: a ring corridor around a solid central block (see :data:`HALL_LAYOUTS`); ``size``
            picks the layout: ``compact`` (default: 4.4 x 3.6 m, corridor 1.4 m, see
            :func:`_compact_hall`) or ``large`` (10 x 8 m, corridor 2.2 m, see :func:`_hall`).
            The seed changes only the textures of its unique pieces.

    ``size`` applies to ``hall`` only (None = its default); giving it for another kind raises
    :class:`DataError`.
    """
    if kind not in SCENE_KINDS:
        raise DataError(f"unknown synthetic scene kind {kind!r}; valid: {', '.join(SCENE_KINDS)}")
    if kind == "hall":
        size = hall_size(size)
        return _compact_hall(seed) if size == "compact" else _hall(seed)
    if size is not None:
        raise DataError(f"scene size {size!r} applies only to kind 'hall', not {kind!r}")
    rng = np.random.default_rng(seed)
    room = _room(rng)
    if kind == "empty":
        return Scene(room, (), name=f"empty-{seed}")
    objects = (*_table_with_objects(rng), *_wall_furniture(rng, room))
    return Scene(room, tuple(objects), name=f"room-{seed}")


# ----------------------------------------------------------------------------------------------
# The hall: a ring corridor around a central block, for loop-closure benchmarks.


@dataclass(frozen=True)
class HallLayout:
    """Where the walls, the block and the repeated furniture of one hall size are.

    Attributes:
        half_size: half extents (x, y) of the floor, metres (the hall is :data:`HALL_HEIGHT` high).
        block_half_size: half extents (x, y) of the solid full-height central block.
        wall_band: furniture stays within this distance of its wall (outer wall or block face).
        repeat_spots: (x, y of the wall behind it) of each copy of the repeated furniture set, in
            the order the anticlockwise ``laps`` path passes them. All copies face -y (so they
            are shaded alike) and their x and y differ by multiples of every period of their
            textures (grain off), so they render identically.
    """

    half_size: tuple[float, float]
    block_half_size: tuple[float, float]
    wall_band: float
    repeat_spots: tuple[tuple[float, float], ...]

    @property
    def corridor_width(self) -> tuple[float, float]:
        """(east/west, north/south) corridor widths, metres."""
        return (self.half_size[0] - self.block_half_size[0], self.half_size[1] - self.block_half_size[1])


HALL_SIZES = ("compact", "large")
"""Layouts of the ``hall`` scene (and of the ``laps`` path around it); the first is the default."""
HALL_LAYOUTS: dict[str, HallLayout] = {
    "compact": HallLayout((2.2, 1.8), (0.8, 0.4), 0.38, ((1.5, 1.8), (-0.3, 1.8), (-1.5, 1.8))),
    "large": HallLayout((5.0, 4.0), (2.8, 1.8), 0.42, ((-0.6, -1.8), (1.8, -1.8), (1.8, 4.0), (-1.8, 4.0))),
}
"""``compact``: 4.4 x 3.6 m around a 1.6 x 0.8 m block (corridors 1.4 m), three copies of the
repeated set, all on the outer north wall: at x = 1.5 (facing the east corridor), -0.3 and -1.5
(1.8 and 1.2 m apart: multiples of the wall's and floor's 0.3 m checker period too).
``large``: 10 x 8 m around a 5.6 x 3.6 m block (corridors 2.2 m), four copies: two against the
block's south face, two against the outer north wall."""
HALL_HEIGHT = 3.0
_FACADE = 0.02
"""Thickness of the panels that give the block's east, north and west faces their own textures."""


def hall_size(size: str | None) -> str:
    """``size`` checked against :data:`HALL_SIZES` (None -> the default, ``compact``)."""
    if size is None:
        return HALL_SIZES[0]
    if size not in HALL_SIZES:
        raise DataError(f"unknown hall size {size!r}; valid: {', '.join(HALL_SIZES)}")
    return size


def _repeat_set(x: float, y_back: float) -> list[Primitive]:
    """The large hall's repeated furniture: a cabinet (0.9 x 0.4 x 0.8 m) against the surface
    at ``y = y_back`` (facing -y), a vase on it and a picture above it. Textures are fixed and
    periodic (0.1 and 0.2 m; see :class:`HallLayout`) so that every copy looks exactly the same."""
    body = Texture("stripes", (0.55, 0.40, 0.25), (0.93, 0.70, 0.25), scale=0.2, direction=(0.0, 0.0, 1.0), seed=41, grain=0.0)
    vase = Texture("checker", (0.85, 0.33, 0.22), (0.90, 0.88, 0.80), scale=0.05, seed=42, grain=0.0)
    picture = Texture("checker", (0.20, 0.22, 0.28), (0.30, 0.75, 0.75), scale=0.1, seed=43, grain=0.0)
    return [
        Box((x, y_back - 0.2, 0.4), (0.45, 0.2, 0.4), body, mesh_bottom=False),
        Cylinder((x + 0.25, y_back - 0.2, 0.8), 0.08, 0.3, vase, mesh_bottom=False),
        Box((x, y_back - 0.02, 1.55), (0.35, 0.02, 0.25), picture),
    ]


def _hall_groups(objects: list[Primitive], repeats: list[list[Primitive]], block: Box, facades: list[Box],
                 mat: Box) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """``repeat_k`` (one per copy), ``plain_east`` (outer east wall, east facade, mat),
    ``plain_west`` (outer west wall) and ``block`` (block and facades) surface ids."""
    ids = {id(obj): 6 + i for i, obj in enumerate(objects)}  # every object here is one primitive
    groups = [(f"repeat_{k}", tuple(ids[id(p)] for p in piece)) for k, piece in enumerate(repeats)]
    groups.append(("plain_east", (ROOM_FACES.index("wall_x_hi"), ids[id(facades[0])], ids[id(mat)])))
    groups.append(("plain_west", (ROOM_FACES.index("wall_x_lo"),)))
    groups.append(("block", (ids[id(block)], *(ids[id(f)] for f in facades))))
    return tuple(groups)


def _hall(seed: int) -> Scene:
    """The large hall (``size=large``), walked anticlockwise by the ``laps`` trajectory.

    Layout (world metres; floor x in [-5, 5], y in [-4, 4]; block x in [-2.8, 2.8], y in [-1.8, 1.8]):
        south corridor (y < -1.8): outer wall wood, with a bench, a poster and a plant; the block's
            south face has vertical stripes, the repeated set at x = -0.6 and x = +1.8 and an
            extinguisher near its west end.
        east corridor (x > 2.8, |y| < 1.8): plain (solid, no grain) outer wall, plain block face
            and a plain floor mat; nothing else (group ``plain_east``).
        north corridor (y > 1.8): outer wall checkered, the repeated set at x = +1.8 and x = -1.8
            (same wall and floor pattern behind both); the block's north face has noise, a poster
            and a bin.
        west corridor (x < -2.8): plain outer wall with nothing in front (group ``plain_west``);
            the block's west face is wood with a shelf and a crate.
        corners: a column (NE), a ball (NW) and a pot (SW) against the north/south walls.
    Floor checker (0.6 m period) and the north wall have no grain, so the two north copies have
    identical surroundings too. Groups: ``repeat_0`` .. ``repeat_3`` (in
    ``HALL_LAYOUTS["large"].repeat_spots`` order), ``plain_east``, ``plain_west``, ``block``.
    """
    layout = HALL_LAYOUTS["large"]
    rng = np.random.default_rng([seed, 0x4A11])
    tex = lambda: _random_texture(rng, scale_range=(0.06, 0.2), patterns=("checker", "stripes", "noise", "wood"))  # noqa: E731
    room = _hall_room(rng, layout, wood_scale=(0.3, 0.4), checker_scale=0.3, ceiling_scale=0.5)
    block, facades, mat = _hall_block(rng, layout, stripe_scale=0.4, facade_scale=(0.25, 0.4), mat_overhang=0.0)
    repeats = [_repeat_set(x, y) for x, y in layout.repeat_spots]
    return _hall_scene(room, block, facades, mat, repeats, _large_hall_pieces(layout, tex), f"hall-{seed}")


def _hall_room(rng: np.random.Generator, layout: HallLayout, *, wood_scale: tuple[float, float],
               checker_scale: float, ceiling_scale: float) -> Room:
    """A hall's walls, floor and ceiling: wood south (a random pair of colours, a scale drawn in
    ``wood_scale``), plain east and west, a grainless checker north wall and floor of period
    ``2 * checker_scale``, a noisy ceiling. Draws from ``rng`` in a fixed order."""
    hx, hy = layout.half_size
    a, b = _pair(rng)
    south = Texture("wood", a, b, scale=float(rng.uniform(*wood_scale)), direction=(1.0, 0.0, 0.0),
                    seed=int(rng.integers(0, 2**31 - 1)))
    east = Texture("solid", (0.86, 0.84, 0.78), grain=0.0)
    north = Texture("checker", (0.90, 0.88, 0.80), (0.60, 0.35, 0.70), scale=checker_scale, seed=44, grain=0.0)
    west = Texture("solid", (0.72, 0.80, 0.86), grain=0.0)
    floor = Texture("checker", (0.55, 0.40, 0.25), (0.75, 0.80, 0.35), scale=checker_scale, seed=45, grain=0.0)
    ceiling = Texture("noise", (0.92, 0.92, 0.88), (0.70, 0.72, 0.78), scale=ceiling_scale,
                      seed=int(rng.integers(0, 2**31 - 1)))
    return Room((-hx, -hy, 0.0), (hx, hy, HALL_HEIGHT), (west, east, south, north, floor, ceiling))


def _hall_block(rng: np.random.Generator, layout: HallLayout, *, stripe_scale: float,
                facade_scale: tuple[float, float], mat_overhang: float) -> tuple[Box, list[Box], Box]:
    """A hall's central block (grainless stripes of ``stripe_scale``), its east, north and west
    facades (plain, noise and wood, scales drawn in ``facade_scale``) and the east corridor's
    plain floor mat, reaching ``mat_overhang`` past the block's ends. Draws from ``rng`` in a
    fixed order."""
    hx, _ = layout.half_size
    bx, by = layout.block_half_size
    half_h = HALL_HEIGHT / 2
    block = Box((0.0, 0.0, half_h), (bx, by, half_h),
                Texture("stripes", (0.30, 0.55, 0.80), (0.90, 0.88, 0.80), scale=stripe_scale, direction=(1.0, 0.0, 0.0),
                        seed=46, grain=0.0),
                mesh_bottom=False)
    t = _FACADE / 2
    a, b = _pair(rng)
    facades = [
        Box((bx + t, 0.0, half_h), (t, by + _FACADE, half_h), Texture("solid", (0.80, 0.80, 0.82), grain=0.0), mesh_bottom=False),
        Box((0.0, by + t, half_h), (bx, t, half_h),
            Texture("noise", a, b, scale=float(rng.uniform(*facade_scale)), seed=int(rng.integers(0, 2**31 - 1))),
            mesh_bottom=False),
        Box((-bx - t, 0.0, half_h), (t, by + _FACADE, half_h),
            Texture("wood", *_pair(rng), scale=float(rng.uniform(*facade_scale)), direction=(0.0, 0.0, 1.0),
                    seed=int(rng.integers(0, 2**31 - 1))), mesh_bottom=False),
    ]
    mat = Box(((bx + _FACADE + hx) / 2, 0.0, 0.005), ((hx - bx - _FACADE) / 2 - 0.02, by + mat_overhang, 0.005),
              Texture("solid", (0.45, 0.50, 0.48), grain=0.0), mesh_bottom=False)
    return block, facades, mat


def _hall_scene(room: Room, block: Box, facades: list[Box], mat: Box, repeats: list[list[Primitive]],
                unique: list[Primitive], name: str) -> Scene:
    """The hall ``name``: its objects in the order block, facades, mat, the repeated sets, the
    other pieces, with its groups (:func:`_hall_groups`)."""
    objects: list[Primitive] = [block, *facades, mat]
    for piece in repeats:
        objects.extend(piece)
    objects.extend(unique)
    return Scene(room, tuple(objects), name=name, groups=_hall_groups(objects, repeats, block, facades, mat))


def _large_hall_pieces(layout: HallLayout, tex: Callable[[], Texture]) -> list[Primitive]:
    """The large hall's furniture but the repeated sets (see :func:`_hall`), textured by
    ``tex()`` in this order."""
    hx, hy = layout.half_size
    bx, by = layout.block_half_size
    face = by + _FACADE  # the north and west pieces stand against the facades
    return [
        # South corridor: bench, poster and plant on the outer wall; extinguisher at the block.
        Box((-2.6, -hy + 0.2, 0.22), (0.7, 0.2, 0.22), tex(), mesh_bottom=False),
        Box((0.3, -hy + 0.02, 1.6), (0.5, 0.02, 0.35), tex()),
        Cylinder((2.1, -hy + 0.22, 0.0), 0.18, 0.55, tex(), mesh_bottom=False),
        Sphere((2.1, -hy + 0.22, 0.75), 0.2, tex()),
        Cylinder((-2.4, -by - 0.1, 0.0), 0.08, 0.5, Texture("stripes", (0.85, 0.33, 0.22), (0.20, 0.22, 0.28), scale=0.12,
                                                             direction=(0.0, 0.0, 1.0), seed=47), mesh_bottom=False),
        # North corridor: a column in the NE corner; a poster and a bin at the block.
        Cylinder((4.2, hy - 0.25, 0.0), 0.17, 1.0, tex(), mesh_bottom=False),
        Box((-0.8, face + 0.02, 1.5), (0.4, 0.02, 0.3), tex()),
        Cylinder((0.3, face + 0.2, 0.0), 0.18, 0.6, tex(), mesh_bottom=False),
        # West corridor: a shelf and a crate at the block; a ball (NW) and a pot (SW) in the corners.
        Box((-bx - _FACADE - 0.15, 0.6, 0.7), (0.15, 0.45, 0.7), tex(), mesh_bottom=False),
        Box((-bx - _FACADE - 0.18, -0.9, 0.2), (0.18, 0.25, 0.2), tex(), mesh_bottom=False),
        Sphere((-4.1, hy - 0.22, 0.2), 0.2, tex()),
        Cylinder((-4.2, -hy + 0.22, 0.0), 0.2, 0.6, tex(), mesh_bottom=False),
    ]

def _compact_repeat_set(x: float, y_back: float) -> list[Primitive]:
    """The compact hall's repeated furniture: a cabinet (0.5 x 0.24 x 0.7 m) against the surface
    at ``y = y_back`` (facing -y), a vase on it and a picture (0.4 x 0.3 m) above it. Textures
    are fixed and periodic (periods 0.1 and 0.2 m, grain off; see :class:`HallLayout`)."""
    body = Texture("stripes", (0.55, 0.40, 0.25), (0.93, 0.70, 0.25), scale=0.14, direction=(0.0, 0.0, 1.0), seed=41, grain=0.0)
    vase = Texture("checker", (0.85, 0.33, 0.22), (0.90, 0.88, 0.80), scale=0.05, seed=42, grain=0.0)
    picture = Texture("checker", (0.20, 0.22, 0.28), (0.30, 0.75, 0.75), scale=0.1, seed=43, grain=0.0)
    return [
        Box((x, y_back - 0.12, 0.35), (0.25, 0.12, 0.35), body, mesh_bottom=False),
        Cylinder((x + 0.12, y_back - 0.12, 0.7), 0.06, 0.22, vase, mesh_bottom=False),
        Box((x, y_back - 0.01, 1.3), (0.2, 0.01, 0.15), picture),
    ]


def _compact_hall(seed: int) -> Scene:
    """The compact hall (``size=compact``, the default), walked anticlockwise by ``laps``.

    The large hall's ingredients (:func:`_hall`) scaled to 1.4 m corridors, with textures about
    half as coarse (the walls are about half as far). Every piece within 0.8 m of the path rises
    at most 0.92 m or is a flat panel 0.02 m deep, so a camera 0.55-0.8 m from the block at
    1.35-1.55 m keeps 0.5 m from everything. From this close the walls at the corridors' ends
    fill most views: the path looks at the east wall along the south corridor, at the north wall
    along the east one, at the west wall along the north one and at the south wall along the
    west one. Layout (world metres; floor x in [-2.2, 2.2], y in [-1.8, 1.8]; block x in
    [-0.8, 0.8], y in [-0.4, 0.4]):
        south corridor (y < -0.4): outer wall wood, with a bench, a poster and a plant; the block's
            south face has vertical stripes and an extinguisher.
        east end (x > 0.8): plain (solid, no grain) outer wall, plain block facade and a plain
            floor mat reaching 0.5 m past the block's ends (``plain_east``); nothing else but a
            textured panel on the outer wall's south end (y in [-1.75, -0.95]), in view from the
            south corridor. Nearly all plain while the path rounds the south-east corner.
        north corridor (y > 0.4): outer wall checkered (no grain, 0.3 m period) with the repeated
            set at x = +1.5 (seen head-on from the east corridor), -0.3 and -1.5 (seen along the
            north corridor); the same wall and floor pattern lie behind each. The block's north
            facade has noise, a poster and a bin.
        west end (x < -0.8): plain outer wall (``plain_west``) with a textured panel on its
            north end (y in [0.95, 1.75]), in view from the north corridor; nearly all plain while
            the path rounds the north-west corner. The block's west facade is wood with a crate
            and a small picture.
        corners: a column (NE), a ball (NW) and a pot (SW) against the north/south walls.
    Groups: ``repeat_0`` .. ``repeat_2`` (in ``HALL_LAYOUTS["compact"].repeat_spots`` order:
    east to west, as the path passes them), ``plain_east``, ``plain_west``, ``block``.
    """
    layout = HALL_LAYOUTS["compact"]
    rng = np.random.default_rng([seed, 0xC0A11])
    tex = lambda: _random_texture(rng, scale_range=(0.05, 0.12), patterns=("checker", "stripes", "noise", "wood"))  # noqa: E731
    room = _hall_room(rng, layout, wood_scale=(0.15, 0.2), checker_scale=0.15, ceiling_scale=0.3)
    block, facades, mat = _hall_block(rng, layout, stripe_scale=0.15, facade_scale=(0.12, 0.18), mat_overhang=0.5)
    repeats = [_compact_repeat_set(x, y) for x, y in layout.repeat_spots]
    panel = lambda: _random_texture(rng, scale_range=(0.06, 0.15), patterns=("checker", "noise", "wood"))  # noqa: E731
    return _hall_scene(room, block, facades, mat, repeats, _compact_hall_pieces(layout, tex, panel),
                       f"hall-compact-{seed}")


def _compact_hall_pieces(layout: HallLayout, tex: Callable[[], Texture], panel: Callable[[], Texture]) -> list[Primitive]:
    """The compact hall's furniture but the repeated sets (see :func:`_compact_hall`),
    textured by ``tex()`` and ``panel()`` in this order."""
    hx, hy = layout.half_size
    bx, by = layout.block_half_size
    face = by + _FACADE  # the north and west pieces stand against the facades
    return [
        # South corridor: bench, poster and plant on the outer wall; extinguisher at the block.
        Box((-1.25, -hy + 0.15, 0.2), (0.4, 0.15, 0.2), tex(), mesh_bottom=False),
        Box((-0.15, -hy + 0.01, 1.45), (0.3, 0.01, 0.22), tex()),
        Cylinder((1.15, -hy + 0.17, 0.0), 0.14, 0.45, tex(), mesh_bottom=False),
        Sphere((1.15, -hy + 0.17, 0.6), 0.16, tex()),
        Cylinder((-0.6, -by - 0.07, 0.0), 0.06, 0.45, Texture("stripes", (0.85, 0.33, 0.22), (0.20, 0.22, 0.28), scale=0.08,
                                                              direction=(0.0, 0.0, 1.0), seed=47), mesh_bottom=False),
        # The end walls' panels, where the south and north corridors look at them.
        Box((hx - 0.01, -1.35, 1.25), (0.01, 0.4, 0.85), panel()),
        Box((-hx + 0.01, 1.35, 1.25), (0.01, 0.4, 0.85), panel()),
        # North corridor: a column in the NE corner; a poster and a bin at the block.
        Cylinder((hx - 0.22, hy - 0.22, 0.0), 0.12, 0.8, tex(), mesh_bottom=False),
        Box((-0.3, face + 0.01, 1.4), (0.25, 0.01, 0.18), tex()),
        Cylinder((0.45, face + 0.13, 0.0), 0.12, 0.45, tex(), mesh_bottom=False),
        # West corridor: a crate and a picture at the block; a ball (NW) and a pot (SW) in the corners.
        Box((-bx - _FACADE - 0.14, -0.12, 0.18), (0.14, 0.2, 0.18), tex(), mesh_bottom=False),
        Box((-bx - _FACADE - 0.01, 0.15, 1.35), (0.01, 0.18, 0.14), tex()),
        Sphere((-hx + 0.2, hy - 0.2, 0.18), 0.18, tex()),
        Cylinder((-hx + 0.2, -hy + 0.2, 0.0), 0.16, 0.5, tex(), mesh_bottom=False),
    ]
