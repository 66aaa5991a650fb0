"""Maps as the runtime holds them: keyframes, a submap (voxels + decoder + pose), the map set.

A ``SubMap`` owns its sparse voxels, its decoder and its keyframes, all in the map's own
frame; ``T_world_map`` places it in the world (paper: Loop Closure based Multi-maps). A
single-map run has one submap with ``T_world_map = I``.

Maps are related in two ways: a map started because the camera left its predecessor's
region has that map as ``parent`` (the tracking chain relates them), and an accepted loop
links two maps (``MapSet.links``). Maps connected through either form one *group* whose
poses are known relative to each other; a map started after a tracking failure has no
parent and floats in its own group until a loop joins it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from .config import SLAMConfig
from .decoder import Decoder
from .fine_color import FineColor
from .frames import TensorFrame
from .render import MapView
from .voxels import SparseVoxelMap, lookup_sorted


@dataclass
class Keyframe:
    """A keyframe kept for windowed optimisation.

    ``frame`` holds its images at the pipeline resolution (None when loaded from a
    checkpoint, which stores poses only); K (3, 3) float32; ``T_map_cam`` (4, 4) float32 is
    refined by bundle adjustment.
    """

    frame_index: int
    timestamp: float
    frame: "TensorFrame | None"
    K: torch.Tensor
    T_map_cam: torch.Tensor
    descriptor: np.ndarray | None = None
    odometry_covariance: np.ndarray | None = None
    """(6, 6) twist order (rho, omega): how uncertain tracking left this keyframe's pose
    relative to the same camera's previous keyframe (summed per-frame covariances; the
    keyframe pose graph's odometry edge). None: unknown."""


def optimised_voxel_mask(corner_updates: torch.Tensor, voxel_corners: torch.Tensor,
                         min_updates: int) -> torch.Tensor:
    """(Nv,) bool: every corner of the voxel got a gradient in >= min_updates mapping steps.
    corner_updates (Nc,) int, voxel_corners (Nv, 8) rows into it."""
    return (corner_updates[voxel_corners] >= min_updates).all(1)


@dataclass
class SubMap:
    map_id: int
    agent: int
    voxels: SparseVoxelMap
    decoder: Decoder
    T_world_map: torch.Tensor
    keyframes: list[Keyframe] = field(default_factory=list)
    corner_updates: torch.Tensor | None = None
    """(Nc,) int32: mapping steps in which each embedding row got a gradient (None: unknown,
    e.g. a checkpoint written before it existed; every voxel then counts as optimised)."""
    surface_codes: torch.Tensor | None = None
    """Sorted Morton codes of the voxels that held an observed surface point (a depth pixel
    back-projected with its pose); None: unknown (every voxel may hold surface)."""
    parent: int | None = None
    """The map this one continues (started by ``region``), None for an agent's first map
    and for a map started after a tracking failure."""
    reason: str = "start"
    """Why the map was started: ``start``, ``region`` or ``tracking_failure``."""
    T_parent_map: torch.Tensor | None = None
    """(4, 4) this map's pose in its parent's frame when it was started: the tracking chain's
    measurement of their relation (the pose graph's sequential edge)."""
    fine: FineColor | None = None
    """The fine colour level (``slam.fine_color``), None without one (``fine_color.levels`` 0,
    or a checkpoint written before it existed)."""

    @classmethod
    def create(cls, map_id: int, agent: int, config: SLAMConfig, device: torch.device,
               T_world_map: torch.Tensor | None = None, seed: int = 0) -> "SubMap":
        """An empty map (random corner embeddings are allocated with its voxels)."""
        torch.manual_seed(seed + map_id)
        voxels = SparseVoxelMap(config.voxel.voxel_size, config.voxel.embed_dim,
                                config.voxel.embed_init_std, device=device, seed=seed + map_id)
        decoder = Decoder(config.decoder, config.voxel.embed_dim).to(device)
        T = torch.eye(4, device=device) if T_world_map is None else T_world_map.to(device)
        fine = FineColor(config.fine_color, seed + map_id).to(device) if config.fine_color.levels else None
        return cls(map_id, agent, voxels, decoder, T, fine=fine)

    def view(self) -> MapView:
        return MapView.of(self.voxels)

    def updates(self) -> torch.Tensor:
        """``corner_updates`` padded with zeros to the current embedding rows, (Nc,) int32."""
        n = self.voxels.num_corners
        device = self.voxels.embeddings.device
        counts = self.corner_updates if self.corner_updates is not None else torch.zeros(0, dtype=torch.int32, device=device)
        if counts.numel() < n:
            counts = torch.cat([counts, counts.new_zeros(n - counts.numel())])
            self.corner_updates = counts
        return counts

    def optimised_voxels(self, min_updates: int) -> torch.Tensor:
        """(Nv,) bool: voxels whose 8 corners got a gradient in >= min_updates mapping steps.
        A freshly allocated voxel holds random embeddings whose SDF means nothing yet."""
        if self.corner_updates is None or min_updates <= 0:
            return torch.ones(self.voxels.num_voxels, dtype=torch.bool, device=self.voxels.voxel_codes.device)
        return optimised_voxel_mask(self.updates(), self.voxels.voxel_corners, min_updates)

    def observe_surface(self, codes: torch.Tensor) -> None:
        """Record the Morton codes (N,) of voxels holding observed surface points."""
        old = self.surface_codes if self.surface_codes is not None else codes.new_zeros(0)
        self.surface_codes = torch.unique(torch.cat([old, codes]))

    def surface_voxels(self) -> torch.Tensor:
        """(Nv,) bool: the voxel held an observed surface point (all True when unknown)."""
        if self.surface_codes is None:
            return torch.ones(self.voxels.num_voxels, dtype=torch.bool, device=self.voxels.voxel_codes.device)
        return lookup_sorted(self.surface_codes, self.voxels.voxel_codes) >= 0

    def optimised_view(self, min_updates: int, surface_only: bool = False) -> MapView:
        """The map restricted to ``optimised_voxels`` and, with ``surface_only``, to the
        ``surface_voxels`` (embedding rows unchanged)."""
        keep = self.optimised_voxels(min_updates)
        if surface_only:
            keep = keep & self.surface_voxels()
        v = self.voxels
        if bool(keep.all()):
            return self.view()
        return MapView(v.voxel_codes[keep], v.voxel_corners[keep], v.embeddings, v.voxel_size)

    def memory_bytes(self) -> tuple[int, int]:
        """(embeddings + voxel index + fine level bytes, decoder bytes)."""
        fine = 0 if self.fine is None else self.fine.num_bytes()
        return self.voxels.nbytes() + fine, self.decoder.num_bytes()

    def state_dict(self) -> dict:
        return {
            "map_id": self.map_id,
            "agent": self.agent,
            "voxels": self.voxels.state_dict(),
            "decoder": {k: v.detach().cpu() for k, v in self.decoder.state_dict().items()},
            "T_world_map": self.T_world_map.detach().cpu(),
            "corner_updates": None if self.corner_updates is None else self.corner_updates.cpu(),
            "surface_codes": None if self.surface_codes is None else self.surface_codes.cpu(),
            "parent": self.parent,
            "reason": self.reason,
            "T_parent_map": None if self.T_parent_map is None else self.T_parent_map.detach().cpu(),
            "fine": None if self.fine is None else {k: v.detach().cpu() for k, v in self.fine.state_dict().items()},
            "keyframes": [
                {"frame_index": kf.frame_index, "timestamp": kf.timestamp,
                 "T_map_cam": kf.T_map_cam.detach().cpu(), "K": kf.K.detach().cpu()}
                for kf in self.keyframes
            ],
        }

    @classmethod
    def from_state_dict(cls, state: dict, config: SLAMConfig, device: torch.device | str = "cpu") -> "SubMap":
        voxels = SparseVoxelMap.from_state_dict(state["voxels"], device=device)
        decoder = Decoder(config.decoder, voxels.embed_dim)
        decoder.load_state_dict(state["decoder"])
        decoder.to(device)
        submap = cls(int(state["map_id"]), int(state["agent"]), voxels, decoder,
                     state["T_world_map"].to(device))
        if state.get("corner_updates") is not None:
            submap.corner_updates = state["corner_updates"].to(device)
        if state.get("surface_codes") is not None:
            submap.surface_codes = state["surface_codes"].to(device)
        submap.parent = None if state.get("parent") is None else int(state["parent"])
        submap.reason = str(state.get("reason", "start"))
        if state.get("T_parent_map") is not None:
            submap.T_parent_map = state["T_parent_map"].to(device)
        submap.fine = _fine_from_state(state.get("fine"), config, device)
        # Keyframe images are not stored in checkpoints; only their poses.
        for kf in state.get("keyframes", []):
            submap.keyframes.append(Keyframe(kf["frame_index"], kf["timestamp"], None,
                                             kf["K"].to(device), kf["T_map_cam"].to(device)))
        return submap


def _fine_from_state(state: dict | None, config: SLAMConfig, device) -> FineColor | None:
    """A checkpoint's fine level; None when it has none (written before the level existed or
    without it): its views are the coarse map's, whatever the config now says. The stored
    tables give the level's shape: (R, F) with each level's rows in ``rows``, or, written before
    levels had sizes of their own, (L, T, F)."""
    if state is None:
        return None
    state = dict(state)
    if state["tables"].dim() == 3:
        levels, table, features = state["tables"].shape
        state["tables"] = state["tables"].reshape(levels * table, features)
        state["rows"] = torch.full((levels,), table, dtype=torch.int64)
    rows, features = state["rows"].tolist(), int(state["tables"].shape[1])
    fine = FineColor(replace(config.fine_color, levels=len(rows), features=features,
                             table_log2=max(rows).bit_length() - 1), rows=rows)
    fine.load_state_dict(state)
    return fine.to(device)


@dataclass
class MapSet:
    """All submaps of a run, in creation order; ``config`` says how they were built."""

    config: SLAMConfig
    maps: list[SubMap] = field(default_factory=list)
    links: list[tuple[int, int]] = field(default_factory=list)
    """Pairs of map ids joined by an accepted loop."""

    def by_id(self, map_id: int) -> SubMap:
        for submap in self.maps:
            if submap.map_id == map_id:
                return submap
        raise KeyError(f"no map {map_id}")

    def groups(self) -> dict[int, int]:
        """map id -> the smallest map id of its group (maps related by ``parent`` or by a
        loop link: their relative poses are known)."""
        root = {m.map_id: m.map_id for m in self.maps}

        def find(i: int) -> int:
            while root[i] != i:
                root[i] = root[root[i]]
                i = root[i]
            return i

        pairs = [(m.map_id, m.parent) for m in self.maps if m.parent is not None] + list(self.links)
        for a, b in pairs:
            if a in root and b in root:
                ra, rb = find(a), find(b)
                root[max(ra, rb)] = min(ra, rb)
        return {i: find(i) for i in root}

    def num_voxels(self) -> int:
        return sum(m.voxels.num_voxels for m in self.maps)

    def num_keyframes(self) -> int:
        return sum(len(m.keyframes) for m in self.maps)
