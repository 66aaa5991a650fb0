"""Sparse voxel map indexed by Morton codes (paper: Dynamic Voxel Management).

Voxel ``(i, j, k)`` covers ``[i, i+1) x [j, j+1) x [k, k+1)`` times ``voxel_size`` in the map
frame. Coordinates are offset by ``2**20`` and interleaved into 63-bit Morton codes (21 bits
per axis), so any voxel within about +-200 km (0.2 m voxels) has a code: there are no scene
bounds and no fixed table size. Codes are kept sorted, so lookup is ``torch.searchsorted``.

Learnable embeddings live at voxel *corners*; the 8 corners of a voxel are lattice points
``ijk + {0,1}^3`` shared with its neighbours, so a corner row is allocated once and reused.
The embedding table only grows (``torch.cat``); ``grow_adam_state`` carries an optimiser over.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

MORTON_BITS = 21
MORTON_OFFSET = 1 << (MORTON_BITS - 1)
_COORD_MIN = -MORTON_OFFSET
_COORD_MAX = MORTON_OFFSET - 1

# Masks of the bits that belong to x, y and z in an interleaved code (x is bit 0).
_MASK_X = int("".join("001" for _ in range(MORTON_BITS)), 2)
MORTON_MASKS = (_MASK_X, _MASK_X << 1, _MASK_X << 2)

# Corner offsets in the order used everywhere: bit 0 = x, bit 1 = y, bit 2 = z.
CORNER_OFFSETS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])


def _dilate(v: torch.Tensor) -> torch.Tensor:
    """(N,) int64 in [0, 2^21) -> the same bits spread to every third position."""
    v = v & 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


def _compact(v: torch.Tensor) -> torch.Tensor:
    """Inverse of ``_dilate``: every third bit gathered into the low 21 bits."""
    v = v & 0x1249249249249249
    v = (v | (v >> 2)) & 0x10C30C30C30C30C3
    v = (v | (v >> 4)) & 0x100F00F00F00F00F
    v = (v | (v >> 8)) & 0x1F0000FF0000FF
    v = (v | (v >> 16)) & 0x1F00000000FFFF
    v = (v | (v >> 32)) & 0x1FFFFF
    return v


def morton_encode(ijk: torch.Tensor) -> torch.Tensor:
    """(N, 3) int64 voxel coordinates -> (N,) int64 Morton codes.

    Raises ValueError when a coordinate is outside [-2^20, 2^20).
    Example: ``morton_encode(tensor([[0, 0, 0]]))`` is ``0b100100100...`` (the offset).
    """
    ijk = ijk.to(torch.int64)
    if ijk.numel():
        lo, hi = torch.stack(torch.aminmax(ijk)).tolist()  # one read of the device
        if lo < _COORD_MIN or hi > _COORD_MAX:
            raise ValueError(f"voxel coordinate outside the Morton range [{_COORD_MIN}, {_COORD_MAX}]")
    return morton_encode_unchecked(ijk)


def morton_encode_unchecked(ijk: torch.Tensor) -> torch.Tensor:
    """``morton_encode`` without the range check, which reads the device: for coordinates
    already clamped to [-2^20, 2^20) (the renderers' lookups). (N, 3) int64 -> (N,) int64."""
    u = ijk.to(torch.int64) + MORTON_OFFSET
    return _dilate(u[:, 0]) | (_dilate(u[:, 1]) << 1) | (_dilate(u[:, 2]) << 2)


def morton_decode(codes: torch.Tensor) -> torch.Tensor:
    """(N,) int64 Morton codes -> (N, 3) int64 voxel coordinates."""
    x = _compact(codes)
    y = _compact(codes >> 1)
    z = _compact(codes >> 2)
    return torch.stack([x, y, z], -1) - MORTON_OFFSET


def morton_add(codes: torch.Tensor, offset: tuple[int, int, int]) -> torch.Tensor:
    """(N,) codes of voxels ``ijk`` -> codes of ``ijk + offset`` by dilated-integer addition.

    No decode/encode: each axis' bits are summed in place, carries skipping the other axes'
    bits because those are set to one first. Wraps around at the edge of the Morton range.
    """
    out = torch.zeros_like(codes)
    for axis, delta in enumerate(offset):
        mask = MORTON_MASKS[axis]
        part = codes & mask
        step = _dilate(torch.tensor([delta % (1 << MORTON_BITS)], dtype=torch.int64))[0].item() << axis
        summed = ((part | ~mask) + step) & mask
        out = out | summed
    return out


def voxel_coords_of(points: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """(N, 3) float points in the map frame -> (N, 3) int64 voxel coordinates."""
    return torch.floor(points / voxel_size).to(torch.int64)


def lookup_sorted(sorted_codes: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """Index of each query in ``sorted_codes`` (N,) or -1 where absent. Shapes: (M,) -> (M,)."""
    if sorted_codes.numel() == 0:
        return torch.full_like(queries, -1)
    pos = torch.searchsorted(sorted_codes, queries).clamp(max=sorted_codes.numel() - 1)
    return torch.where(sorted_codes[pos] == queries, pos, torch.full_like(pos, -1))


@dataclass(frozen=True)
class AllocationResult:
    new_voxels: int
    """Voxels that did not exist before this call."""
    observed_voxels: int
    """Distinct voxels hit by the points (new and old)."""
    new_corners: int


class SparseVoxelMap:
    """Sparse voxels with learnable corner embeddings, in one map's own frame.

    Attributes:
        voxel_codes: (Nv,) int64 sorted Morton codes of allocated voxels.
        voxel_corners: (Nv, 8) int64 embedding rows of each voxel's corners, aligned with
            ``voxel_codes``; corner c is at offset ``CORNER_OFFSETS[c]``.
        corner_codes: (Nc,) int64 sorted Morton codes of corner lattice points.
        corner_rows: (Nc,) int64 embedding row of each entry of ``corner_codes``.
        embeddings: (Nc, D) float32 parameter; rows are appended, never moved.
    """

    def __init__(self, voxel_size: float, embed_dim: int = 16, init_std: float = 0.01,
                 device: torch.device | str = "cpu", seed: int = 0):
        self.voxel_size = float(voxel_size)
        self.embed_dim = int(embed_dim)
        self.init_std = float(init_std)
        self.device = torch.device(device)
        self._generator = torch.Generator().manual_seed(seed)
        long = dict(dtype=torch.int64, device=self.device)
        self.voxel_codes = torch.zeros(0, **long)
        self.voxel_corners = torch.zeros(0, 8, **long)
        self.corner_codes = torch.zeros(0, **long)
        self.corner_rows = torch.zeros(0, **long)
        self.embeddings = torch.nn.Parameter(torch.zeros(0, self.embed_dim, device=self.device))
        self.version = 0

    # ----------------------------------------------------------------- queries
    @property
    def num_voxels(self) -> int:
        return int(self.voxel_codes.numel())

    @property
    def num_corners(self) -> int:
        return int(self.embeddings.shape[0])

    def nbytes(self) -> int:
        """Bytes of the learnable embeddings plus the index structures."""
        tensors = (self.voxel_codes, self.voxel_corners, self.corner_codes, self.corner_rows)
        return self.embeddings.numel() * self.embeddings.element_size() + sum(
            t.numel() * t.element_size() for t in tensors
        )

    def voxel_coords(self) -> torch.Tensor:
        """(Nv, 3) int64 coordinates of the allocated voxels, in ``voxel_codes`` order."""
        return morton_decode(self.voxel_codes)

    def find_voxels(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) map-frame points -> (N,) int64 index into ``voxel_codes`` or -1."""
        codes = morton_encode(voxel_coords_of(points, self.voxel_size))
        return lookup_sorted(self.voxel_codes, codes)

    def count_new(self, points: torch.Tensor) -> tuple[int, int]:
        """How many distinct voxels the points hit, and how many of those are not allocated,
        without changing the map (the paper's ``N_o`` and ``N_c`` against allocated voxels).

        The mapper's keyframe test counts against the voxels its keyframes observed instead
        (``slam.mapping``: every frame allocates, so allocated voxels would starve the test);
        this stays for tools that ask about the map itself (``bench_iteration.py``).
        """
        codes = torch.unique(morton_encode(voxel_coords_of(points, self.voxel_size)))
        missing = lookup_sorted(self.voxel_codes, codes) < 0
        return int(codes.numel()), int(missing.sum())

    # -------------------------------------------------------------- allocation
    def allocate(self, points: torch.Tensor) -> AllocationResult:
        """Allocate every voxel that holds one of the (N, 3) map-frame points."""
        codes = torch.unique(morton_encode(voxel_coords_of(points.to(self.device), self.voxel_size)))
        new_codes = codes[lookup_sorted(self.voxel_codes, codes) < 0]
        if new_codes.numel() == 0:
            return AllocationResult(0, int(codes.numel()), 0)
        new_corner_ids, new_corners = self._corner_rows_for(new_codes)
        all_codes = torch.cat([self.voxel_codes, new_codes])
        all_corners = torch.cat([self.voxel_corners, new_corner_ids])
        order = torch.argsort(all_codes)
        self.voxel_codes = all_codes[order]
        self.voxel_corners = all_corners[order]
        self.version += 1
        return AllocationResult(int(new_codes.numel()), int(codes.numel()), new_corners)

    def _corner_rows_for(self, voxel_codes: torch.Tensor) -> tuple[torch.Tensor, int]:
        """Embedding rows (M, 8) of the corners of the given voxels, allocating missing ones."""
        ijk = morton_decode(voxel_codes)
        corners = ijk[:, None, :] + CORNER_OFFSETS.to(self.device)[None]
        corner_codes = morton_encode(corners.reshape(-1, 3))
        unique_codes = torch.unique(corner_codes)
        missing = unique_codes[lookup_sorted(self.corner_codes, unique_codes) < 0]
        if missing.numel():
            first_row = self.num_corners
            rows = torch.arange(first_row, first_row + missing.numel(), device=self.device)
            fresh = torch.randn(missing.numel(), self.embed_dim, generator=self._generator) * self.init_std
            self.embeddings = torch.nn.Parameter(
                torch.cat([self.embeddings.detach(), fresh.to(self.device)]),
                requires_grad=self.embeddings.requires_grad,
            )
            codes = torch.cat([self.corner_codes, missing])
            all_rows = torch.cat([self.corner_rows, rows])
            order = torch.argsort(codes)
            self.corner_codes, self.corner_rows = codes[order], all_rows[order]
        pos = lookup_sorted(self.corner_codes, corner_codes)
        return self.corner_rows[pos].reshape(-1, 8), int(missing.numel())

    # ------------------------------------------------------------- persistence
    def state_dict(self) -> dict[str, torch.Tensor | float | int]:
        return {
            "voxel_size": self.voxel_size,
            "embed_dim": self.embed_dim,
            "init_std": self.init_std,
            "voxel_codes": self.voxel_codes.cpu(),
            "voxel_corners": self.voxel_corners.cpu(),
            "corner_codes": self.corner_codes.cpu(),
            "corner_rows": self.corner_rows.cpu(),
            "embeddings": self.embeddings.detach().cpu(),
            "version": self.version,
        }

    @classmethod
    def from_state_dict(cls, state: dict, device: torch.device | str = "cpu") -> "SparseVoxelMap":
        vmap = cls(state["voxel_size"], state["embed_dim"], state["init_std"], device=device)
        vmap.voxel_codes = state["voxel_codes"].to(device)
        vmap.voxel_corners = state["voxel_corners"].to(device)
        vmap.corner_codes = state["corner_codes"].to(device)
        vmap.corner_rows = state["corner_rows"].to(device)
        vmap.embeddings = torch.nn.Parameter(state["embeddings"].to(device).clone())
        vmap.version = int(state.get("version", 0))
        return vmap


def grow_adam_state(optimizer: torch.optim.Optimizer, old: torch.Tensor, new: torch.nn.Parameter) -> None:
    """Swap parameter ``old`` for the grown ``new`` (more rows) inside an Adam optimiser.

    Moment estimates of existing rows are kept; appended rows start at zero, as a fresh
    parameter would. (N, D) -> (N', D) with N' >= N.
    """
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is old:
                group["params"][i] = new
    state = optimizer.state.pop(old, None)
    if not state:
        return
    grown = {}
    for key, value in state.items():
        if torch.is_tensor(value) and value.shape == old.shape:
            pad = torch.zeros(new.shape[0] - old.shape[0], *old.shape[1:], dtype=value.dtype, device=value.device)
            grown[key] = torch.cat([value, pad])
        else:
            grown[key] = value
    optimizer.state[new] = grown
