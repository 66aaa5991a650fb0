"""Keyframe pose graph: the loop correction inside maps (hierarchical pose optimisation).

Paper: Hierarchical Pose Optimization. The inter-map step (``closing``) moves maps as rigid
bodies; the intra-map step bundle-adjusts each map's keyframes against that map. Neither
undoes drift that accumulated *inside* one map while it was built: on the synthetic laps
path (3 m maps, 780 frames) giving every 100-frame piece its own best rigid alignment to GT
still leaves 10 cm RMSE (benchmarks/README.md, "Where the laps drift comes from"). This
module is the keyframe level of the pose graph the issue asks for: every keyframe of every
map is a node, consecutive keyframes of one camera are tied by what tracking and bundle
adjustment measured between them, and every geometrically verified loop ties its query
keyframe to its match keyframe. Optimised together, a loop bends the trajectory between its
ends instead of shifting whole maps.

What follows from the solution:

- each keyframe's world pose is the graph's; frames follow their latest keyframe
  (``slam.outputs.refine_with_keyframes``);
- each map's ``T_world_map`` becomes the rigid motion that best carries its keyframes from
  their old to their new poses, and the keyframes' poses in the map are re-expressed under
  it; the world's first map keeps its pose (its first keyframe anchors the graph, and the
  world is that map's frame). The neural map itself stays rigid: what is left inside a map
  is the part of the drift that its geometry holds (fixing that needs re-fitting the map to
  the new poses).

Odometry edges get the uncertainty the tracker reported: each tracked frame's curvature
(``TrackingResult.information``) becomes a covariance (``frame_covariance``) that is large
in the directions the view did not fix, and the frames between two keyframes add up. A
stretch where a plain wall fills the view, which drifts along the wall, can then take the
correction a loop brings, instead of the correction being spread evenly over the lap.
Without the tracker's curvature (the Adam tracker) the uncertainty grows with the motion
between the two keyframes (drift per metre and per radian travelled). Loop edges get the
verification's uncertainty, under the robust kernel (a loop that disagrees with the rest is
switched off and reported).

Pure functions: numpy in, numpy out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# pose_graph (gtsam) is imported where the graph is solved: the tracker imports
# frame_covariance and has no use for gtsam.


@dataclass(frozen=True, eq=False)
class KeyframeNode:
    """A keyframe as its map holds it: ``T_map_cam`` (4, 4) float64 in map ``map_id``;
    ``covariance`` (6, 6), twist order (rho, omega), m and rad: of its pose relative to the
    same camera's previous keyframe, summed over the frames tracked in between (None:
    unknown, the distance rule applies)."""

    agent: int
    map_id: int
    frame_index: int
    T_map_cam: np.ndarray
    covariance: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class MapNode:
    """A map: ``T_world_map`` (4, 4) float64; ``parent`` and ``T_parent_map`` (4, 4) as the
    tracking chain measured them when the map was started (None for an agent's first map and
    for a map started after a tracking failure)."""

    map_id: int
    T_world_map: np.ndarray
    parent: int | None = None
    T_parent_map: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class KeyframeLoop:
    """A verified loop between keyframes: ``T_match_query`` (4, 4) is the query keyframe's
    pose in the match keyframe's camera frame, as verification measured it."""

    agent: int
    frame_index: int
    match_agent: int
    match_frame_index: int
    T_match_query: np.ndarray


@dataclass(frozen=True)
class OdometrySigmas:
    """1-sigma of an odometry edge between two keyframes that are ``d`` metres and ``a``
    radians apart: ``translation_m + translation_per_m * d`` and
    ``rotation_rad + rotation_per_rad * a + rotation_per_m * d``."""

    translation_m: float = 0.005
    translation_per_m: float = 0.05
    rotation_rad: float = 0.002
    rotation_per_rad: float = 0.05
    rotation_per_m: float = 0.01

    def of(self, T_a_b: np.ndarray) -> tuple[float, float]:
        d = float(np.linalg.norm(T_a_b[:3, 3]))
        a = _angle(T_a_b[:3, :3])
        return (self.translation_m + self.translation_per_m * d,
                self.rotation_rad + self.rotation_per_rad * a + self.rotation_per_m * d)


@dataclass(frozen=True, eq=False)
class KeyframeGraphResult:
    """``map_poses``: map id -> new T_world_map (4, 4); ``keyframe_poses``: (agent, frame
    index) -> new T_world_cam (4, 4); ``loops_used`` / ``loops_rejected``: loop edges kept
    and switched off by the robust kernel; ``odometry_edges``; ``max_correction_m``: the
    largest move of a keyframe."""

    map_poses: dict[int, np.ndarray]
    keyframe_poses: dict[tuple[int, int], np.ndarray]
    loops_used: int
    loops_rejected: int
    odometry_edges: int
    max_correction_m: float

    def keyframes_in_maps(self, keyframes: list[KeyframeNode]) -> dict[tuple[int, int], np.ndarray]:
        """(agent, frame index) -> the keyframe's new T_map_cam under its map's new pose."""
        return {(k.agent, k.frame_index): np.linalg.solve(self.map_poses[k.map_id],
                                                          self.keyframe_poses[(k.agent, k.frame_index)])
                for k in keyframes}

    def summary(self) -> dict:
        return {"loops_used": self.loops_used, "loops_rejected": self.loops_rejected,
                "odometry_edges": self.odometry_edges, "max_correction_m": round(self.max_correction_m, 4)}


FRAME_SIGMA_M = 0.002
FRAME_SIGMA_RAD = 0.001
"""1-sigma of one tracked frame's pose in its best-observed translation and rotation
direction (``frame_covariance``)."""
MAX_CURVATURE_RATIO = 1e4
"""A direction with less than 1/this of the best direction's curvature counts as unobserved:
its sigma is capped at 100x the best one's."""


def frame_covariance(information: np.ndarray, sigma_m: float = FRAME_SIGMA_M, sigma_rad: float = FRAME_SIGMA_RAD,
                     max_ratio: float = MAX_CURVATURE_RATIO) -> np.ndarray:
    """(6, 6) covariance, twist order (rho, omega), of one tracked frame from the tracker's
    (6, 6) curvature ``information``.

    The curvature's scale depends on the loss's weights and ray count, not on metres, so
    each block (translation, rotation) is taken relative to its own stiffest direction:
    that direction gets ``sigma`` and a direction with k times less curvature sqrt(k) times
    more (k at most ``max_ratio``). Cross terms between the blocks are left out.
    """
    H = 0.5 * (np.asarray(information, np.float64) + np.asarray(information, np.float64).T)
    C = np.zeros((6, 6))
    for block, sigma in ((slice(0, 3), sigma_m), (slice(3, 6), sigma_rad)):
        w, V = np.linalg.eigh(H[block, block])
        top = float(w.max())
        if not np.isfinite(top) or top <= 0:
            C[block, block] = np.eye(3) * (sigma ** 2 * max_ratio)
            continue
        w = np.clip(w, top / max_ratio, None)
        C[block, block] = sigma ** 2 * (V * (top / w)) @ V.T
    return C


def _angle(R: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))


def orthonormal(T: np.ndarray) -> np.ndarray:
    """(4, 4) float64 with its rotation projected onto SO(3) (float32 products drift off it)."""
    out = np.array(T, np.float64, copy=True)
    U, _, Vt = np.linalg.svd(out[:3, :3])
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def odometry_measurement(a: KeyframeNode, b: KeyframeNode, maps: dict[int, MapNode]) -> np.ndarray | None:
    """T_a_b (4, 4) of consecutive keyframes of one camera as tracking related them: in one
    map directly, across a region border through the child map's ``T_parent_map``; None when
    the chain is broken (``b``'s map was started after a tracking failure)."""
    if a.map_id == b.map_id:
        return np.linalg.solve(a.T_map_cam, b.T_map_cam)
    child = maps[b.map_id]
    if child.parent == a.map_id and child.T_parent_map is not None:
        return np.linalg.solve(a.T_map_cam, child.T_parent_map @ b.T_map_cam)
    return None


def rigid_motion(before: list[np.ndarray], after: list[np.ndarray], arm_m: float = 0.5) -> np.ndarray:
    """(4, 4) rigid motion M minimising sum |M p - q|^2 over each pose's centre and three
    points ``arm_m`` along its axes (so that orientation counts, and one pose is enough)."""
    from ..eval.ate import umeyama_alignment

    arms = np.array([[0, 0, 0, 1], [arm_m, 0, 0, 1], [0, arm_m, 0, 1], [0, 0, arm_m, 1]], np.float64).T
    src = np.concatenate([(T @ arms)[:3].T for T in before])
    dst = np.concatenate([(T @ arms)[:3].T for T in after])
    R, t, _ = umeyama_alignment(src, dst, with_scale=False)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return orthonormal(M)


def optimise_keyframe_graph(maps: list[MapNode], keyframes: list[KeyframeNode], loops: list[KeyframeLoop],
                            sigmas: OdometrySigmas = OdometrySigmas(), loop_sigma_m: float = 0.02,
                            loop_sigma_rad: float = 0.01, robust_kernel: str = "huber") -> KeyframeGraphResult:
    """Optimise every keyframe's world pose against odometry and loop edges (module doc).

    maps: every map, the world's first one first (its first keyframe is the anchor; other
    cameras that no loop joined are anchored at their first keyframe). keyframes: every
    keyframe of every map. loops: verified loops between keyframes in ``keyframes`` (others
    are skipped). Returns the new map and keyframe poses.
    """
    from .pose_graph import PoseNode, RelativePoseEdge, optimise_pose_graph

    by_map = {m.map_id: m for m in maps}
    nodes = sorted(keyframes, key=lambda k: (k.agent, k.frame_index))
    key = {(k.agent, k.frame_index): i for i, k in enumerate(nodes)}
    before = {i: orthonormal(by_map[k.map_id].T_world_map @ k.T_map_cam) for i, k in enumerate(nodes)}
    edges: list[RelativePoseEdge] = []
    for i in range(1, len(nodes)):
        a, b = nodes[i - 1], nodes[i]
        if a.agent != b.agent:
            continue
        T_a_b = odometry_measurement(a, b, by_map)
        if T_a_b is None:
            continue
        T_a_b = orthonormal(T_a_b)
        st, sr = sigmas.of(T_a_b)
        edges.append(RelativePoseEdge(i - 1, i, T_a_b, st, sr, kind="sequential", covariance=b.covariance))
    odometry = len(edges)
    for loop in loops:
        a, b = key.get((loop.match_agent, loop.match_frame_index)), key.get((loop.agent, loop.frame_index))
        if a is None or b is None or a == b:
            continue
        edges.append(RelativePoseEdge(a, b, orthonormal(loop.T_match_query), loop_sigma_m, loop_sigma_rad,
                                      kind="loop"))
    if not nodes:
        return KeyframeGraphResult({m.map_id: m.T_world_map for m in maps}, {}, 0, 0, 0, 0.0)
    first = [i for i, k in enumerate(nodes) if k.map_id == maps[0].map_id]
    anchors = [min(first, key=lambda i: nodes[i].frame_index)] if first else []
    solved = optimise_pose_graph([PoseNode(i, T) for i, T in before.items()], edges, anchors,
                                 robust_kernel=robust_kernel, auto_anchor=True)
    after = solved.poses
    map_poses: dict[int, np.ndarray] = {}
    for m in maps:
        members = [i for i, k in enumerate(nodes) if k.map_id == m.map_id]
        if not members or (anchors and m.map_id == maps[0].map_id):
            # The world's first map stays where its anchor keyframe holds the world: a best
            # fit over its keyframes would move the world's origin with them.
            map_poses[m.map_id] = np.asarray(m.T_world_map, np.float64)
            continue
        motion = rigid_motion([before[i] for i in members], [after[i] for i in members])
        map_poses[m.map_id] = orthonormal(motion @ m.T_world_map)
    loop_residuals = [r for r in solved.residuals if r.kind == "loop"]
    rejected = sum(r.rejected for r in loop_residuals)
    moved = max((float(np.linalg.norm(after[i][:3, 3] - before[i][:3, 3])) for i in before), default=0.0)
    return KeyframeGraphResult(map_poses, {(k.agent, k.frame_index): after[i] for i, k in enumerate(nodes)},
                               len(loop_residuals) - rejected, rejected, odometry, moved)
