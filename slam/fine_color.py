"""A finer level of appearance where the surface is: colour detail below
the 0.2 m voxels, at no cost to tracking.

The coarse map (corner embeddings of 0.2 m voxels and the decoder) holds geometry and a
smooth colour: at 1.5 m a voxel spans some 40 pixels of a 320-wide view, so text, keyboard
keys and edges vanish. The fine level adds a colour *residual* ``delta(x)`` at the surface
point ``x`` a pixel sees (its rendered depth along its ray), from a multi-resolution hash
grid (Instant-NGP, Co-SLAM): ``levels`` grids from ``coarsest`` to ``finest`` metres (geometric
steps), each corner hashed into its level's table of rows of ``features`` floats,
trilinearly interpolated, concatenated and mapped to RGB by one linear layer (with
``level_tables`` "surface" a coarser level's table is smaller, as a surface crosses fewer of
its cells):

    C_view = C_coarse + delta(o + D d)        (D: rendered z-depth, d: ray with z = 1)

It is queried only at rendered surface points, so only cells on observed surfaces are ever
written, and the tables bound its memory whatever the scene (``num_bytes``). Mapping trains it
on the residual of its rays, ``|C_coarse.detach() + delta(x.detach()) - C_gt|`` (``fine_loss``):
the coarse embeddings, the decoder and the poses get no gradient from it, so the coarse
optimisation, and tracking, which renders the coarse level only, are exactly as without it.
After the final bundle adjustment ``Mapper.fit_fine_rendered`` (or ``fit_fine``, at the
measured depth) fits it to the keyframes at the surface the coarse map renders for each of
their pixels (``slam.views.coarse_surface``): where 0.2 m voxels put that surface centimetres
off the measured one, the colour lands where views look. Views (``slam.views``) and mesh
vertex colours (``slam.mesh``) add ``delta``.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from . import kernels
from .config_sections import FineColorConfig

HASH_PRIMES = (1, 2654435761, 805459861)
"""Instant-NGP's spatial hash: xor of the integer coordinates times these."""
INIT_SCALE = 1e-4
"""Tables start at U(-1e-4, 1e-4) (Instant-NGP): delta starts near zero."""


def level_cells(config: FineColorConfig) -> torch.Tensor:
    """(L,) float64 cell edges in metres, from ``coarsest`` to ``finest`` in geometric steps.
    Example: coarsest 0.08, finest 0.01, levels 4 -> [0.08, 0.04, 0.02, 0.01]."""
    if config.levels == 1:
        return torch.tensor([config.finest], dtype=torch.float64)
    ratio = (config.finest / config.coarsest) ** (1.0 / (config.levels - 1))
    return torch.tensor([config.coarsest * ratio ** i for i in range(config.levels)], dtype=torch.float64)


CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.int64)
"""(8, 3) corner offsets of a cell, in the order of ``slam.render.trilinear_weights``."""


def level_rows(config: FineColorConfig) -> list[int]:
    """Rows of each level's table, coarsest first: ``2^table_log2`` each (``equal``), or with
    ``level_tables`` "surface" the finest level's ``2^table_log2`` divided by the surface-area
    ratio (cell / finest)^2 rounded to a power of two, at least 16. A surface crosses about
    that many times fewer cells of a coarser level, so its table needs that many fewer rows
    for as few collisions. Example: 4 levels 0.16-0.02 m, table_log2 16 -> [2^10, 2^12, 2^14, 2^16]."""
    rows = 1 << config.table_log2
    if config.level_tables == "equal":
        return [rows] * config.levels
    shrinks = [round(2 * math.log2(cell / config.finest)) for cell in level_cells(config).tolist()]
    return [max(min(16, rows), rows >> min(shrink, config.table_log2)) for shrink in shrinks]


def hash_rows(ijk: torch.Tensor, table_size: int) -> torch.Tensor:
    """(..., 3) int64 cell corners -> (...) int64 rows in [0, table_size) (a power of two)."""
    h = ijk[..., 0] * HASH_PRIMES[0] ^ ijk[..., 1] * HASH_PRIMES[1] ^ ijk[..., 2] * HASH_PRIMES[2]
    return h & (table_size - 1)


def offsets_of(rows: torch.Tensor) -> torch.Tensor:
    """(L,) int64 rows of each level's table -> (L,) int64 first row of each in the flat table."""
    return torch.cumsum(rows, 0) - rows


def corner_rows_and_weights(points: torch.Tensor, cells: torch.Tensor, rows: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 3) map-frame points, (L,) cell edges, (L,) int64 rows of each level's table (powers
    of two) -> rows (N, L, 8) int64 into the flat table (the levels' tables one after another)
    and trilinear weights (N, L, 8) float32 (each row sums to 1).

    The hash is a xor of one term per axis, so each axis' two terms and two weights are formed
    once and the 8 corners combine them (a third of the work of hashing every corner)."""
    x = points.to(torch.float64)[:, None, :] / cells.to(points.device)[None, :, None]   # (N, L, 3)
    base = torch.floor(x)
    frac = (x - base).to(torch.float32)
    ijk = base.to(torch.int64)
    h, w = [], []
    for axis in range(3):  # (N, L, 2) each: the axis' term and weight at offsets 0 and 1
        i = ijk[..., axis]
        h.append(torch.stack([i * HASH_PRIMES[axis], (i + 1) * HASH_PRIMES[axis]], -1))
        w.append(torch.stack([1.0 - frac[..., axis], frac[..., axis]], -1))
    # Corner (a, b, c) at index 4a + 2b + c, the order of CORNERS.
    hashed = (h[0][..., :, None, None] ^ h[1][..., None, :, None] ^ h[2][..., None, None, :]).flatten(-3)
    weights = (w[0][..., :, None, None] * w[1][..., None, :, None] * w[2][..., None, None, :]).flatten(-3)
    rows = rows.to(points.device)
    return (hashed & (rows - 1)[None, :, None]) + offsets_of(rows)[None, :, None], weights


def hash_features(points: torch.Tensor, tables: torch.Tensor, cells: torch.Tensor, rows: torch.Tensor
                  ) -> torch.Tensor:
    """(N, 3) points, flat tables (R, F), (L,) cell edges, (L,) int64 rows of each level's
    table (summing to R) -> (N, L * F) interpolated features."""
    features = tables.shape[1]
    index, weights = corner_rows_and_weights(points, cells, rows)
    corner = tables[index]                                                               # (N, L, 8, F)
    return (weights[..., None] * corner).sum(2).reshape(points.shape[0], cells.numel() * features)


def hash_features_reference(points: torch.Tensor, tables: torch.Tensor, cells: torch.Tensor,
                            rows: torch.Tensor) -> torch.Tensor:
    """``hash_features`` one point, level and corner at a time (the tests' reference)."""
    starts = [0]
    for n in rows.tolist()[:-1]:
        starts.append(starts[-1] + n)
    out = []
    for p in points.to(torch.float64):
        row = []
        for level, cell in enumerate(cells.tolist()):
            x = p / cell
            base = torch.floor(x)
            acc = torch.zeros(tables.shape[1], dtype=torch.float64)
            for corner in CORNERS:
                ijk = base.to(torch.int64) + corner
                w = torch.prod(torch.where(corner.bool(), x - base, 1 - (x - base)))
                acc += w * tables[starts[level] + int(hash_rows(ijk, int(rows[level])))].to(torch.float64)
            row.append(acc)
        out.append(torch.cat(row))
    return torch.stack(out).to(tables.dtype) if out else tables.new_zeros(0, cells.numel() * tables.shape[1])


class FineColor(nn.Module):
    """The fine level: one flat hash table (R, F) holding every level's rows one after another
    (``rows``: (L,) of each level's) and a linear head (L * F -> 3)."""

    def __init__(self, config: FineColorConfig, seed: int = 0, rows: list[int] | None = None):
        """``rows``: each level's table size (a checkpoint's); default ``level_rows(config)``."""
        super().__init__()
        if config.levels < 1:
            raise ValueError("a FineColor needs fine_color.levels >= 1")
        rows = level_rows(config) if rows is None else [int(r) for r in rows]
        if len(rows) != config.levels or any(r < 1 or r & (r - 1) for r in rows):
            raise ValueError(f"a FineColor needs one power-of-two table size per level, got {rows}")
        self.config = config
        # Its own generator: the coarse map's random draws stay those of a run without it.
        gen = torch.Generator().manual_seed(seed)
        width = config.levels * config.features
        tables = (torch.rand(sum(rows), config.features, generator=gen) * 2 - 1) * INIT_SCALE
        self.tables = nn.Parameter(tables)
        self.head = nn.Linear(width, 3)
        with torch.no_grad():
            self.head.weight.copy_(torch.randn(3, width, generator=gen) / math.sqrt(width))
            self.head.bias.zero_()
        self.register_buffer("cells", level_cells(config))  # stored: a checkpoint keeps its levels
        self.register_buffer("rows", torch.tensor(rows, dtype=torch.int64))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) map-frame points -> (N, 3) colour residual. Without gradients (views,
        meshes) on float32 CPU tensors, the numba kernel computes the features (a 640x480
        view's 250k points: a tenth of the torch path's time); else ``hash_features``."""
        if not torch.is_grad_enabled() and kernels.use_numba(points, self.tables):
            from .kernels.fused import hash_grid

            return self.head(hash_grid(points, self.cells, self.tables, self.rows, HASH_PRIMES))
        return self.head(hash_features(points, self.tables, self.cells, self.rows))

    def num_bytes(self) -> int:
        return sum(p.numel() * p.element_size() for p in self.parameters())


def surface_points(origins: torch.Tensor, dirs: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """(R, 3) ray origins and directions (z = 1 in the camera, so ``t`` is z-depth), (R,)
    depth -> (R, 3) points ``o + D d``."""
    return origins + depth[:, None] * dirs


def fine_loss(fine: FineColor, origins: torch.Tensor, dirs: torch.Tensor, color: torch.Tensor,
              depth: torch.Tensor, use: torch.Tensor, rgb_gt: torch.Tensor) -> torch.Tensor:
    """Mean L1 of ``color + delta(x) - rgb_gt`` over the rays in ``use`` (R,) bool, with the
    coarse colour (R, 3), the depth (R,) and the rays (R, 3) detached: only ``fine`` learns.
    Masked sums, no read back from the device."""
    x = surface_points(origins.detach(), dirs.detach(), depth.detach())
    residual = (color.detach() + fine(x) - rgb_gt).abs()
    use_f = use.to(residual.dtype)
    return (residual * use_f[:, None]).sum() / (3.0 * use_f.sum()).clamp(min=1.0)


def with_fine(fine: FineColor | None, origins: torch.Tensor, dirs: torch.Tensor, color: torch.Tensor,
              depth: torch.Tensor, surface: torch.Tensor) -> torch.Tensor:
    """The view colour: (R, 3) coarse ``color`` plus ``delta`` at the surface point of each
    ray in ``surface`` (R,) bool, clamped to [0, 1]; ``color`` itself without a fine level."""
    if fine is None or not bool(surface.any()):
        return color
    idx = torch.nonzero(surface, as_tuple=True)[0]
    out = color.clone()
    out[idx] = (color[idx] + fine(surface_points(origins[idx], dirs[idx], depth[idx]))).clamp(0.0, 1.0)
    return out


def coarse_point_color(points: torch.Tensor, view, decoder) -> tuple[torch.Tensor, torch.Tensor]:
    """The coarse map's colour at (N, 3) map-frame points, one decoder sample each (no volume
    rendering) -> colour (N, 3) and (N,) bool: the point lies in an allocated voxel."""
    from .render import color_of_hidden, decode_samples

    voxel = view.find(torch.floor(points / view.voxel_size).to(torch.int64))
    inside = voxel >= 0
    color = torch.zeros_like(points)
    idx = torch.nonzero(inside, as_tuple=True)[0]
    if idx.numel():
        _, hidden = decode_samples(points[idx], voxel[idx], view, decoder)
        color[idx] = color_of_hidden(decoder, hidden)
    return color, inside


def fit_loss(fine: FineColor, points: torch.Tensor, coarse: torch.Tensor, use: torch.Tensor,
             rgb_gt: torch.Tensor) -> torch.Tensor:
    """Mean L1 of ``coarse + delta(points) - rgb_gt`` over ``use`` (N,) bool: points (N, 3)
    observed surface points, coarse (N, 3) the coarse colour there (constant)."""
    residual = (coarse + fine(points) - rgb_gt).abs()
    use_f = use.to(residual.dtype)
    return (residual * use_f[:, None]).sum() / (3.0 * use_f.sum()).clamp(min=1.0)
