"""The loop closer: for every new keyframe, loop detection and hierarchical pose optimisation.

Paper: Loop Closure based Multi-maps. For each keyframe added by the mapper:

1. **Appearance check** (``slam.loop.database``): its global descriptor is compared with
   every keyframe in the database (all maps, all agents); the best ``top_k`` above the
   scene-adaptive threshold are candidates.
2. **Geometric verification** (``slam.loop.verification``): features + PnP, refinement by
   tracking against the candidate map, the voxel and depth check.
3. **Inter-map optimisation**: the verified pose of the query camera in the target map
   gives the relative pose of the two maps. If they were not related yet (a floating map
   after a tracking failure, another agent's maps), the source map's whole group is first
   moved rigidly onto the target; then a pose graph over all map poses (``pose_graph``:
   sequential edges from the tracking chain between a map and the one it continues, loop
   edges from verified loops, a robust kernel on loops, the world's first map anchored)
   spreads the correction over the maps between.
4. **Intra-map optimisation**: global bundle adjustment of the two joined maps' keyframes
   (``Mapper.refine_map``).
5. **Keyframe pose graph** (``keyframe_graph``, at the end of the run after the global
   bundle adjustment): every keyframe a node, odometry between consecutive keyframes and
   every verified loop (also those the map-level kernel refused: maps bent by their own
   drift disagree with a loop that keyframes agree with) as edges; the drift inside maps,
   which moving maps rigidly leaves, is corrected on the trajectory and each map takes the
   rigid pose that best fits its keyframes.

Within one group the frame-gap rule keeps near-in-time keyframes (the previous map's last
views of a region border) from counting as loops. Every candidate's scores are kept.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..config import SLAMConfig
from ..data.frame import Frame
from ..events import LoopEvent
from ..features import FrameFeatures, detect_features, loop_feature_count
from ..geometry import se3_inverse
from ..maps import Keyframe, SubMap
from .database import KeyframeDatabase, KeyframeEntry, make_descriptor
from .keyframe_graph import (KeyframeGraphResult, KeyframeLoop, KeyframeNode, MapNode, optimise_keyframe_graph,
                             orthonormal)
from .pose_graph import PoseNode, RelativePoseEdge, optimise_pose_graph
from .verification import LoopVerification, frozen_in_map_frame, refinement_tracker, verify_candidate


def measured_relative_pose(T_map_match: np.ndarray, T_map_query: np.ndarray) -> dict:
    """What a verified loop measured, for ``run.json``: the query keyframe's pose in the match
    keyframe's camera frame (``T_match_query``, 4x4 rows, metres) and its size (distance and
    angle), so that a loop can be checked against ground truth by its pose error
    (``slam.eval.loops``), not only by how far apart its frames are."""
    T = np.linalg.solve(np.asarray(T_map_match, np.float64), np.asarray(T_map_query, np.float64))
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1.0, 1.0)))
    return {"T_match_query": np.round(T, 6).tolist(), "relative_m": round(float(np.linalg.norm(T[:3, 3])), 4),
            "relative_deg": round(float(angle), 3)}


def loop_json(loop: LoopEvent) -> dict:
    """An accepted loop as ``run.json``'s ``loop_closures`` lists it (poses left out)."""
    return {"timestamp": loop.timestamp, "match_timestamp": loop.match_timestamp, "map": loop.map_id,
            "match_map": loop.match_map, "agent": loop.agent, "match_agent": loop.match_agent,
            "frame_index": loop.frame_index, "match_frame_index": loop.match_frame_index,
            "T_match_query": loop.scores.get("T_match_query"),
            "scores": {k: v for k, v in loop.scores.items() if k != "T_match_query"}}


@dataclass
class _Timings:
    ms: dict[str, list[float]] = field(default_factory=lambda: {
        "descriptor": [], "query": [], "verification": [], "optimisation": [], "keyframe_graph": []})

    def add(self, name: str, seconds: float) -> None:
        self.ms[name].append(seconds * 1e3)

    def summary(self) -> dict[str, float]:
        """Mean milliseconds per keyframe (descriptor, query), per verified candidate
        (verification) and per accepted loop (optimisation), and their counts."""
        out: dict[str, float] = {}
        for k, v in self.ms.items():
            out[f"{k}_mean_ms"] = round(float(np.mean(v)), 2) if v else 0.0
            out[f"{k}_count"] = len(v)
        return out


def _np(T: torch.Tensor) -> np.ndarray:
    """(4, 4) float64 copy with its rotation re-orthonormalised: poses composed in float32
    drift off SO(3) by ~1e-6 per product, more than the pose graph accepts."""
    return orthonormal(T.detach().cpu().numpy())


class LoopCloser:
    """Keyframe database, verification and pose optimisation, driven by the mapper."""

    def __init__(self, config: SLAMConfig, device: torch.device, seed: int = 0):
        import cv2

        self.config = config
        self.device = device
        self.database = KeyframeDatabase.from_config(config.loop)
        self.descriptor = make_descriptor(config.loop)
        count = loop_feature_count(config)
        self._orb = cv2.ORB_create(count)
        # Verification wants many corners with depth: at 160 x 120 the default FAST threshold
        # (20) and 31 px patches leave ~30 per synthetic frame and two views of one place
        # 15 cm apart share ~15 PnP inliers; threshold 7 and 15 px patches give ~150
        # features and 42-45 inliers (320 x 240: 29-48 -> 151-161). The descriptor keeps
        # the default detector, which its words and thresholds were measured with.
        self._orb_verify = cv2.ORB_create(count, fastThreshold=7, edgeThreshold=15, patchSize=15)
        self._tracker = refinement_tracker(config, device, seed)
        self._gen = torch.Generator().manual_seed(seed + 7)
        self.closures: list[LoopEvent] = []
        self.candidates: list[dict] = []
        """Every verified candidate's record (accepted or not), for the user to inspect."""
        self.rejected = 0
        self.loop_edges: list[RelativePoseEdge] = []
        self.keyframe_loops: list[KeyframeLoop] = []
        """Every verified loop as a keyframe-to-keyframe measurement (the keyframe graph's)."""
        self.timings = _Timings()
        self._frozen_cache: dict[int, tuple[int, object]] = {}
        self._map_revision: dict[int, int] = {}
        self._last_closed: dict[tuple[int, int], int] = {}
        """(map, other map) -> the map's keyframe count when a loop last joined them."""

    # ----------------------------------------------------------------- public
    def add_keyframe(self, mapper, submap: SubMap, keyframe: Keyframe, frame: Frame,
                     features: FrameFeatures | None = None) -> list[LoopEvent]:
        """Detect and close loops for ``keyframe`` (just added to ``submap``; ``frame`` its
        images as numpy, at pipeline resolution). ``features``: the frame's ORB features as the
        appearance check's detector finds them, when the tracker already detected them
        (``features.tracking_features_serve_loops``); None: detected here. Returns the
        accepted loops (at most one)."""
        t0 = time.perf_counter()
        descriptor, verify_features = self._describe(frame, features)
        self.timings.add("descriptor", time.perf_counter() - t0)
        t0 = time.perf_counter()
        candidates = self._candidates(mapper, submap, keyframe, descriptor)
        self.timings.add("query", time.perf_counter() - t0)
        self.database.add(KeyframeEntry(submap.map_id, submap.agent, keyframe.frame_index, keyframe.timestamp,
                                        descriptor, verify_features))
        for cand in candidates[:self.config.loop.top_k]:
            closure = self._try_candidate(mapper, submap, keyframe, cand, verify_features)
            if closure is not None:
                return [closure]
        return []

    # ------------------------------------------------------ add_keyframe's steps
    def _describe(self, frame: Frame, features: FrameFeatures | None) -> tuple[np.ndarray, FrameFeatures]:
        """The keyframe's global descriptor (from the appearance detector's features) and its
        features for geometric verification (a second detector, tuned for many corners)."""
        max_depth = self.config.voxel.max_depth
        if features is None:
            features = detect_features(frame, self._orb.getMaxFeatures(), max_depth, self._orb)
        descriptor = self.descriptor.describe(frame, features)
        return descriptor, detect_features(frame, self._orb_verify.getMaxFeatures(), max_depth, self._orb_verify)

    def _candidates(self, mapper, submap: SubMap, keyframe: Keyframe, descriptor: np.ndarray) -> list:
        """The database's candidates for ``keyframe`` that passed the appearance check and may
        close a loop (``_eligible``, not ``_recently_closed``), best first."""
        c = self.config.loop
        groups = mapper.maps.groups()
        found = self.database.query(descriptor, map_id=submap.map_id, agent=submap.agent,
                                    frame_index=keyframe.frame_index, top_k=4 * c.top_k,
                                    min_frame_gap=c.min_frame_gap)
        return [cand for cand in found if cand.passed and self._eligible(cand.entry, submap, keyframe, groups)
                and not self._recently_closed(submap, cand.entry.map_id)]

    def _try_candidate(self, mapper, submap: SubMap, keyframe: Keyframe, cand,
                       features: FrameFeatures) -> LoopEvent | None:
        """Verify one candidate and, when verified, close the loop; its record is kept either
        way. Returns the accepted loop (None: not verified, or the pose graph refused it)."""
        t0 = time.perf_counter()
        target = mapper.maps.by_id(cand.entry.map_id)
        match_kf = _keyframe(target, cand.entry.frame_index)
        if match_kf is None or keyframe.frame is None:
            return None
        result = verify_candidate(keyframe.frame, features, cand.entry.features, match_kf.T_map_cam,
                                  lambda: self._frozen(mapper, target), self.config, self._tracker, self._gen)
        self.timings.add("verification", time.perf_counter() - t0)
        record = {"agent": submap.agent, "map": submap.map_id, "frame_index": keyframe.frame_index,
                  "timestamp": keyframe.timestamp, "match_agent": target.agent, "match_map": target.map_id,
                  "match_frame_index": match_kf.frame_index, "match_timestamp": match_kf.timestamp,
                  "similarity": round(float(cand.similarity), 4), "threshold": round(float(cand.threshold), 4),
                  **result.scores(), "verified": result.accepted, "accepted": result.accepted}
        if result.T_map_query is not None:
            record.update(measured_relative_pose(_np(match_kf.T_map_cam), result.T_map_query))
        if result.accepted:
            assert result.T_map_query is not None
            self.keyframe_loops.append(KeyframeLoop(
                submap.agent, keyframe.frame_index, target.agent, match_kf.frame_index,
                np.linalg.solve(_np(match_kf.T_map_cam), np.asarray(result.T_map_query, np.float64))))
            t0 = time.perf_counter()
            closure = self._close(mapper, submap, keyframe, target, match_kf, result, record)
            self.timings.add("optimisation", time.perf_counter() - t0)
            if closure is not None:
                self.candidates.append(record)
                return closure
        self.rejected += 1
        record["accepted"] = False
        self.candidates.append(record)
        return None

    def optimise_keyframes(self, mapper) -> KeyframeGraphResult | None:
        """The keyframe pose graph over every map (module doc, step 5); writes the new map
        poses and keyframe poses into ``mapper``'s maps. None (nothing changed) without
        verified loops."""
        if not self.keyframe_loops or not self.config.loop.keyframe_graph:
            return None
        t0 = time.perf_counter()
        maps = mapper.maps.maps
        nodes = [MapNode(m.map_id, _np(m.T_world_map), m.parent,
                         None if m.T_parent_map is None else _np(m.T_parent_map)) for m in maps]
        keyframes = [KeyframeNode(m.agent, m.map_id, kf.frame_index, _np(kf.T_map_cam), kf.odometry_covariance)
                     for m in maps for kf in m.keyframes]
        c = self.config.loop
        solved = optimise_keyframe_graph(nodes, keyframes, self.keyframe_loops,
                                         loop_sigma_m=c.loop_sigma_m, loop_sigma_rad=c.loop_sigma_rad)
        in_maps = solved.keyframes_in_maps(keyframes)
        for m in maps:
            m.T_world_map = torch.tensor(solved.map_poses[m.map_id], dtype=torch.float32, device=self.device)
            for kf in m.keyframes:
                kf.T_map_cam = torch.tensor(in_maps[(m.agent, kf.frame_index)], dtype=kf.T_map_cam.dtype,
                                            device=kf.T_map_cam.device)
        self.timings.add("keyframe_graph", time.perf_counter() - t0)
        return solved

    def closures_json(self) -> list[dict]:
        return [loop_json(c) for c in self.closures]

    def timings_ms(self) -> dict[str, float]:
        return self.timings.summary()

    # ---------------------------------------------------------------- helpers
    def _eligible(self, entry: KeyframeEntry, submap: SubMap, keyframe: Keyframe, groups: dict[int, int]) -> bool:
        """A candidate of the query's own group (whose relative pose is already known) must
        be ``min_frame_gap`` frames older if it is the same agent's: the maps just before
        share the view across a region border without closing any loop."""
        if entry.map_id == submap.map_id and not self.config.loop.same_map:
            return False
        same_group = groups.get(entry.map_id) == groups.get(submap.map_id)
        if not same_group or entry.agent != submap.agent:
            return True
        return keyframe.frame_index - entry.frame_index >= self.config.loop.min_frame_gap

    def _recently_closed(self, source: SubMap, target_map: int) -> bool:
        """Whether this pair of maps was joined by a loop fewer than
        ``loop.keyframes_between_loops`` keyframes of the source map ago: one loop already
        aligned them, and each closure costs an intra-map bundle adjustment."""
        last = self._last_closed.get((source.map_id, target_map))
        return last is not None and len(source.keyframes) - last < self.config.loop.keyframes_between_loops

    def _frozen(self, mapper, target: SubMap):
        """The target map frozen in its own frame; cached for maps that are not being mapped."""
        active = any(m is target for m in mapper.active.values())
        rev = self._map_revision.get(target.map_id, 0)
        cached = self._frozen_cache.get(target.map_id)
        if not active and cached is not None and cached[0] == rev:
            return cached[1]
        fmap = frozen_in_map_frame(mapper.snapshot(target), self.config, self.device)
        if not active:
            self._frozen_cache[target.map_id] = (rev, fmap)
        return fmap

    def _close(self, mapper, source: SubMap, keyframe: Keyframe, target: SubMap, match_kf: Keyframe,
               result: LoopVerification, record: dict) -> LoopEvent | None:
        """Hierarchical pose optimisation for a verified loop (None: the pose graph refused it)."""
        c = self.config.loop
        assert result.T_map_query is not None
        if source is not target:
            T_tar_q = torch.as_tensor(result.T_map_query, dtype=torch.float32, device=self.device)
            T_tar_src = T_tar_q @ se3_inverse(keyframe.T_map_cam)  # source map in the target's frame
            edge = RelativePoseEdge(target.map_id, source.map_id, _np(T_tar_src), c.loop_sigma_m, c.loop_sigma_rad,
                                    kind="loop")
            if not self._inter_map(mapper, source, target, edge):
                record["reason"] = "the pose graph rejected the loop as an outlier"
                return None
        # Intra-map: every keyframe of the joined maps against its map (0 iterations: left to
        # the end-of-run keyframe graph and global bundle adjustment; see the cpu preset).
        for submap in {id(source): source, id(target): target}.values() if c.intra_map_iterations > 0 else ():
            mapper.refine_map(submap, c.intra_map_iterations, self.config.mapping.final_rays)
            self._map_revision[submap.map_id] = self._map_revision.get(submap.map_id, 0) + 1
        closure = LoopEvent(
            source.agent, source.map_id, keyframe.frame_index, keyframe.timestamp, target.agent, target.map_id,
            match_kf.frame_index, match_kf.timestamp, _np(keyframe.T_map_cam), _np(match_kf.T_map_cam), {k: v for k, v in record.items() if k not in (
                "agent", "map", "frame_index", "timestamp", "match_agent", "match_map", "match_frame_index",
                "match_timestamp", "verified", "accepted")})
        self.closures.append(closure)
        for pair in ((source.map_id, target.map_id), (target.map_id, source.map_id)):
            self._last_closed[pair] = len(mapper.maps.by_id(pair[0]).keyframes)
        return closure

    def _inter_map(self, mapper, source: SubMap, target: SubMap, edge: RelativePoseEdge) -> bool:
        """Join ``source`` to ``target`` by ``edge`` and re-optimise every map pose; False
        (nothing changed) when the robust kernel rejects the new edge."""
        maps = mapper.maps
        before = {m.map_id: m.T_world_map.clone() for m in maps.maps}
        groups = maps.groups()
        g_src, g_tar = groups[source.map_id], groups[target.map_id]
        if g_src != g_tar:
            # Not related yet: move the newer group (the one without the older root, so the
            # world's first map never moves) rigidly onto the other first, so that the
            # optimisation starts near its solution.
            T_tar_src = torch.tensor(np.array(edge.T_a_b), dtype=torch.float32, device=self.device)
            if g_src > g_tar:
                moving, delta = g_src, target.T_world_map @ T_tar_src @ se3_inverse(source.T_world_map)
            else:
                moving, delta = g_tar, source.T_world_map @ se3_inverse(T_tar_src) @ se3_inverse(target.T_world_map)
            for m in maps.maps:
                if groups[m.map_id] == moving:
                    m.T_world_map = delta @ m.T_world_map
        nodes = [PoseNode(m.map_id, _np(m.T_world_map)) for m in maps.maps]
        seq = self.config.loop
        edges = [RelativePoseEdge(m.parent, m.map_id, _np(m.T_parent_map), seq.sequential_sigma_m,
                                  seq.sequential_sigma_rad, kind="sequential")
                 for m in maps.maps if m.parent is not None and m.T_parent_map is not None]
        edges += self.loop_edges + [edge]
        anchors = {maps.maps[0].map_id}
        solved = optimise_pose_graph(nodes, edges, anchors, robust_kernel="huber", auto_anchor=True)
        if len(edges) - 1 in solved.rejected_edges:
            for m in maps.maps:
                m.T_world_map = before[m.map_id]
            return False
        for m in maps.maps:
            m.T_world_map = torch.tensor(np.array(solved.poses[m.map_id]), dtype=torch.float32, device=self.device)
        self.loop_edges.append(edge)
        maps.links.append((target.map_id, source.map_id))
        return True


def _keyframe(submap: SubMap, frame_index: int) -> Keyframe | None:
    for kf in submap.keyframes:
        if kf.frame_index == frame_index:
            return kf
    return None
