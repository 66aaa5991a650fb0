"""Pose graph over maps (or keyframes), solved with gtsam Levenberg-Marquardt.

Paper: Vox-Fusion++, hierarchical pose optimisation, inter-map step. Each node is a pose
``T_world`` (4, 4) float64: map-to-world for submaps, camera-to-world for keyframes; metres.
An edge ``a -> b`` measures ``T_a_b`` with the meaning ``T_world_b ~= T_world_a @ T_a_b``;
"sequential" edges come from one camera's tracking chain, "loop" edges from loop closure.

Gauge: a pose graph only fixes relative poses, so each connected component (an agent's
maps, or several agents once a loop joined them) needs at least one anchor, a strong prior
that pins a node at its input pose. Components without one raise ``ValueError`` naming the
keys, unless ``auto_anchor=True``, which anchors the component's smallest key (keys are
handed out in creation order, so that is its oldest node).

Tangent convention: gtsam's Pose3 tangent is ``(omega, rho)``, rotation first, so the
sigmas here are built as ``[s_r, s_r, s_r, s_t, s_t, s_t]``; slam.geometry uses
``(rho, omega)``, nothing here mixes the two.

Pure functions: numpy in, numpy out; no torch.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import gtsam
import numpy as np

ROBUST_KERNELS = ("huber", "cauchy")
# Standard widths (95% asymptotic efficiency on Gaussian inliers), applied by gtsam to the
# Mahalanobis norm of the whole 6-vector residual of a factor.
DEFAULT_KERNEL_WIDTH = {"huber": 1.345, "cauchy": 2.3849}
# sqrt of the chi-square 99.9% quantile with 6 degrees of freedom (22.46).
DEFAULT_OUTLIER_THRESHOLD = 4.74
DEFAULT_ANCHOR_SIGMAS = (1e-6, 1e-6)

_ROT_TOL = 1e-5
_OMEGA_RHO = [3, 4, 5, 0, 1, 2]
"""slam.geometry's twist (rho, omega) reordered into gtsam's Pose3 tangent (omega, rho)."""


def _as_pose(T, what: str) -> np.ndarray:
    """Validate a rigid transform and return a read-only (4, 4) float64 copy."""
    M = np.array(T, dtype=np.float64, copy=True)
    if M.shape != (4, 4):
        raise ValueError(f"{what}: expected a (4, 4) pose, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError(f"{what}: pose has non-finite entries")
    R = M[:3, :3]
    if (np.abs(R.T @ R - np.eye(3)).max() > _ROT_TOL or np.linalg.det(R) <= 0
            or np.abs(M[3] - [0, 0, 0, 1]).max() > 1e-9):
        raise ValueError(f"{what}: not a rigid transform (rotation not orthonormal, or bad last row)")
    M.flags.writeable = False
    return M


def _as_key(k, what: str) -> int:
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)):
        raise ValueError(f"{what}: key must be an int, got {k!r}")
    k = int(k)
    if not 0 <= k < 2**63:
        raise ValueError(f"{what}: key must be in [0, 2**63), got {k}")
    return k


def _positive(x, what: str) -> float:
    x = float(x)
    if not (np.isfinite(x) and x > 0):
        raise ValueError(f"{what} must be a positive finite number, got {x}")
    return x


@dataclass(frozen=True, eq=False)
class PoseNode:
    """A node: ``key`` (int >= 0; creation order) and its initial ``T_world`` (4, 4) float64."""

    key: int
    T_world: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "key", _as_key(self.key, "PoseNode"))
        object.__setattr__(self, "T_world", _as_pose(self.T_world, f"PoseNode {self.key}"))


@dataclass(frozen=True, eq=False)
class RelativePoseEdge:
    """A measurement ``T_a_b`` (4, 4): ``T_world_b ~= T_world_a @ T_a_b``.

    Sigmas are 1-sigma per axis: metres for translation, radians for rotation. ``kind`` is a
    free label ("sequential", "loop", ...). ``robust``: whether the graph's robust kernel
    applies to this edge; None (default) means ``kind != "sequential"`` (tracking chains are
    trusted, loop closures may be wrong).
    """

    a: int
    b: int
    T_a_b: np.ndarray
    sigma_translation_m: float = 0.05
    sigma_rotation_rad: float = 0.02
    kind: str = "loop"
    robust: bool | None = None
    covariance: np.ndarray | None = None
    """(6, 6) full covariance, twist order (rho, omega) as slam.geometry (translation first),
    used instead of the sigmas when given."""

    def __post_init__(self):
        a, b = _as_key(self.a, "RelativePoseEdge.a"), _as_key(self.b, "RelativePoseEdge.b")
        if a == b:
            raise ValueError(f"RelativePoseEdge: self-edge on key {a}")
        object.__setattr__(self, "a", a)
        object.__setattr__(self, "b", b)
        object.__setattr__(self, "T_a_b", _as_pose(self.T_a_b, f"RelativePoseEdge {a}->{b}"))
        object.__setattr__(self, "sigma_translation_m",
                           _positive(self.sigma_translation_m, "sigma_translation_m"))
        object.__setattr__(self, "sigma_rotation_rad",
                           _positive(self.sigma_rotation_rad, "sigma_rotation_rad"))
        object.__setattr__(self, "kind", str(self.kind))
        if self.robust is None:
            object.__setattr__(self, "robust", self.kind != "sequential")
        else:
            object.__setattr__(self, "robust", bool(self.robust))
        if self.covariance is not None:
            C = np.array(self.covariance, dtype=np.float64)
            if C.shape != (6, 6) or not np.all(np.isfinite(C)) or np.linalg.eigvalsh(0.5 * (C + C.T)).min() <= 0:
                raise ValueError(f"RelativePoseEdge {a}->{b}: covariance must be a finite positive-definite (6, 6)")
            object.__setattr__(self, "covariance", 0.5 * (C + C.T))

            object.__setattr__(self, "_gtsam_covariance", self.covariance[np.ix_(_OMEGA_RHO, _OMEGA_RHO)])

    def noise_model(self):
        """gtsam's Gaussian noise model of the edge, in Pose3's tangent order (omega, rho)."""
        if self.covariance is None:
            return gtsam.noiseModel.Diagonal.Sigmas(self.sigmas)
        return gtsam.noiseModel.Gaussian.Covariance(self._gtsam_covariance)

    def whitened(self, error: np.ndarray) -> float:
        """Mahalanobis norm of gtsam's 6-vector error (omega, rho) under this edge's noise."""
        if self.covariance is None:
            return float(np.linalg.norm(error / self.sigmas))
        return float(np.sqrt(error @ np.linalg.solve(self._gtsam_covariance, error)))

    @property
    def sigmas(self) -> np.ndarray:
        """(6,) float64 in gtsam Pose3 tangent order: rotation (rad) x3, translation (m) x3."""
        return np.array([self.sigma_rotation_rad] * 3 + [self.sigma_translation_m] * 3)


@dataclass(frozen=True, eq=False)
class EdgeResidual:
    """Residual of edge ``index`` after optimisation.

    ``E = T_a_b^-1 @ T_world_a^-1 @ T_world_b``; ``translation_m = |E[:3, 3]|``,
    ``rotation_rad`` = angle of ``E[:3, :3]``. ``whitened_norm`` is the Mahalanobis norm of
    gtsam's 6-vector error under the edge's sigmas (no robust weighting), ``weight`` the
    robust kernel's weight at that norm (1 for non-robust edges). ``rejected``: the edge is
    robust and ``whitened_norm > outlier_threshold``, i.e. the kernel has effectively
    switched it off.
    """

    index: int
    a: int
    b: int
    kind: str
    translation_m: float
    rotation_rad: float
    whitened_norm: float
    weight: float
    robust: bool
    rejected: bool


@dataclass(frozen=True, eq=False)
class PoseGraphResult:
    """Output of :func:`optimise_pose_graph`.

    ``poses``: key -> optimised (4, 4) float64. ``initial_error`` / ``final_error``: gtsam's
    objective (0.5 * sum of robust losses of whitened residuals, priors included) at the
    input and at the solution. ``residuals``: one per edge, in input order. ``anchored``:
    all anchored keys; ``auto_anchored``: the ones added by ``auto_anchor``.
    """

    poses: dict[int, np.ndarray]
    initial_error: float
    final_error: float
    iterations: int
    residuals: tuple[EdgeResidual, ...]
    anchored: tuple[int, ...]
    auto_anchored: tuple[int, ...]
    components: tuple[frozenset[int], ...]

    @property
    def rejected_edges(self) -> tuple[int, ...]:
        """Indices (into the input edges) of edges the robust kernel rejected."""
        return tuple(r.index for r in self.residuals if r.rejected)

    def nodes(self) -> list[PoseNode]:
        """The optimised poses as PoseNodes, sorted by key."""
        return [PoseNode(k, self.poses[k]) for k in sorted(self.poses)]


def components(nodes: Iterable[PoseNode | int], edges: Iterable[RelativePoseEdge]) -> list[set[int]]:
    """Connected components of the graph (edges taken as undirected).

    ``nodes``: PoseNodes or bare keys; edge endpoints not among them are added. Returns a
    list of key sets sorted by their smallest key; isolated nodes are singleton sets.
    """
    parent: dict[int, int] = {}

    def find(x: int) -> int:
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    def add(x: int) -> None:
        parent.setdefault(x, x)

    for n in nodes:
        add(n.key if isinstance(n, PoseNode) else _as_key(n, "components"))
    for e in edges:
        add(e.a)
        add(e.b)
        ra, rb = find(e.a), find(e.b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, set[int]] = {}
    for k in parent:
        groups.setdefault(find(k), set()).add(k)
    return sorted(groups.values(), key=min)


def _to_gtsam(T: np.ndarray) -> gtsam.Pose3:
    # Project the rotation onto SO(3) so gtsam gets an exactly orthonormal matrix.
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return gtsam.Pose3(gtsam.Rot3(R), np.ascontiguousarray(T[:3, 3]))


def _rotation_angle(R: np.ndarray) -> float:
    vee = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.arctan2(np.linalg.norm(vee) / 2, (np.trace(R) - 1) / 2))


def _kernel(name: str, width: float):
    if name == "huber":
        return gtsam.noiseModel.mEstimator.Huber.Create(width)
    return gtsam.noiseModel.mEstimator.Cauchy.Create(width)


def optimise_pose_graph(
    nodes: Iterable[PoseNode],
    edges: Iterable[RelativePoseEdge],
    anchors: Mapping[int, tuple[float, float]] | Iterable[int],
    robust_kernel: str | None = "huber",
    *,
    kernel_width: float | None = None,
    outlier_threshold: float = DEFAULT_OUTLIER_THRESHOLD,
    auto_anchor: bool = False,
    max_iterations: int = 100,
    relative_error_tol: float = 1e-9,
    absolute_error_tol: float = 1e-12,
) -> PoseGraphResult:
    """Optimise node poses against the edges with Levenberg-Marquardt.

    nodes: PoseNodes with unique keys; their ``T_world`` (4, 4) is the initial guess.
    edges: RelativePoseEdges between node keys (BetweenFactorPose3 each).
    anchors: key -> ``(sigma_translation_m, sigma_rotation_rad)`` of a prior at the node's
        input pose, or an iterable of keys for the default strong prior
        ``DEFAULT_ANCHOR_SIGMAS`` (1e-6 m, 1e-6 rad), i.e. fixed. Several are fine (one per
        agent component); every connected component needs at least one.
    robust_kernel: "huber", "cauchy" or None; wraps the noise model of edges with
        ``edge.robust`` (default: non-"sequential" edges) in gtsam.noiseModel.Robust.
    kernel_width: the m-estimator's k in whitened units (default 1.345 huber, 2.3849 cauchy).
    outlier_threshold: whitened norm above which a robust edge is reported as rejected.
    auto_anchor: anchor the smallest (oldest) key of each unanchored component with the
        default strong prior instead of raising.

    Raises ValueError on duplicate keys, edges to unknown keys, unknown anchors, an unknown
    kernel, or (without auto_anchor) components without an anchor, naming their keys.
    """
    nodes = list(nodes)
    edges = list(edges)
    width, outlier_threshold = _checked_options(robust_kernel, kernel_width, outlier_threshold, max_iterations)
    initial = _initial_poses(nodes, edges)
    anchor_sigmas = _anchor_sigmas(anchors, initial)
    comps = components(nodes, edges)
    auto = _anchor_free_components(comps, anchor_sigmas, auto_anchor)
    if not nodes:
        return PoseGraphResult({}, 0.0, 0.0, 0, (), (), (), ())

    graph, values, factors, kernels = _factor_graph(initial, anchor_sigmas, edges, robust_kernel, width)
    initial_error = float(graph.error(values))
    solution, iterations = _levenberg_marquardt(graph, values, max_iterations, relative_error_tol,
                                                absolute_error_tol)
    final_error = float(graph.error(solution))

    poses = {k: np.array(solution.atPose3(k).matrix(), dtype=np.float64) for k in initial}
    residuals = tuple(_edge_residual(i, e, f, kernel, poses, solution, outlier_threshold)
                      for i, (e, f, kernel) in enumerate(zip(edges, factors, kernels)))
    return PoseGraphResult(
        poses=poses,
        initial_error=initial_error,
        final_error=final_error,
        iterations=iterations,
        residuals=residuals,
        anchored=tuple(sorted(anchor_sigmas)),
        auto_anchored=tuple(sorted(auto)),
        components=tuple(frozenset(c) for c in comps),
    )


def _checked_options(robust_kernel: str | None, kernel_width: float | None, outlier_threshold: float,
                     max_iterations: int) -> tuple[float | None, float]:
    """The robust kernel's width (None without a kernel) and the outlier threshold, validated;
    ValueError on an unknown kernel, a non-positive width or threshold, or no iterations."""
    if robust_kernel is not None and robust_kernel not in ROBUST_KERNELS:
        raise ValueError(f"robust_kernel must be one of {ROBUST_KERNELS} or None, got {robust_kernel!r}")
    width = None
    if robust_kernel is not None:
        width = _positive(DEFAULT_KERNEL_WIDTH[robust_kernel] if kernel_width is None else kernel_width,
                          "kernel_width")
    outlier_threshold = _positive(outlier_threshold, "outlier_threshold")
    if int(max_iterations) < 1:
        raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
    return width, outlier_threshold


def _initial_poses(nodes: list[PoseNode], edges: list[RelativePoseEdge]) -> dict[int, np.ndarray]:
    """key -> input pose of each node; ValueError on a non-node, a duplicate key, a non-edge
    or an edge to an unknown key."""
    initial: dict[int, np.ndarray] = {}
    for n in nodes:
        if not isinstance(n, PoseNode):
            raise ValueError(f"nodes must be PoseNode, got {type(n).__name__}")
        if n.key in initial:
            raise ValueError(f"duplicate node key {n.key}")
        initial[n.key] = n.T_world
    for i, e in enumerate(edges):
        if not isinstance(e, RelativePoseEdge):
            raise ValueError(f"edges must be RelativePoseEdge, got {type(e).__name__}")
        missing = [k for k in (e.a, e.b) if k not in initial]
        if missing:
            raise ValueError(f"edge {i} ({e.a}->{e.b}, {e.kind}) refers to unknown node keys {missing}")
    return initial


def _anchor_sigmas(anchors: Mapping[int, tuple[float, float]] | Iterable[int],
                   initial: dict[int, np.ndarray]) -> dict[int, tuple[float, float]]:
    """key -> (sigma_translation_m, sigma_rotation_rad) of each anchor's prior; ValueError on
    an anchor of no node."""
    if isinstance(anchors, Mapping):
        anchor_sigmas = {_as_key(k, "anchor"): (_positive(v[0], "anchor sigma_t"), _positive(v[1], "anchor sigma_r"))
                         for k, v in anchors.items()}
    else:
        anchor_sigmas = {_as_key(k, "anchor"): DEFAULT_ANCHOR_SIGMAS for k in anchors}
    unknown = sorted(k for k in anchor_sigmas if k not in initial)
    if unknown:
        raise ValueError(f"anchors refer to unknown node keys {unknown}")
    return anchor_sigmas


def _anchor_free_components(comps: list[set[int]], anchor_sigmas: dict[int, tuple[float, float]],
                            auto_anchor: bool) -> list[int]:
    """Anchors the smallest key of each component without an anchor (added to
    ``anchor_sigmas``) and returns those keys; without ``auto_anchor`` such a component is a
    ValueError naming the keys."""
    auto: list[int] = []
    unanchored = [c for c in comps if not (c & anchor_sigmas.keys())]
    if unanchored:
        if not auto_anchor:
            listing = "; ".join(str(sorted(c)) for c in unanchored)
            raise ValueError(
                f"{len(unanchored)} pose-graph component(s) have no anchor, so their gauge is free: "
                f"{listing}. Anchor one key in each (e.g. the agent's first map) or pass auto_anchor=True."
            )
        for c in unanchored:
            anchor_sigmas[min(c)] = DEFAULT_ANCHOR_SIGMAS
            auto.append(min(c))
    return auto


def _factor_graph(initial: dict[int, np.ndarray], anchor_sigmas: dict[int, tuple[float, float]],
                  edges: list[RelativePoseEdge], robust_kernel: str | None, width: float | None):
    """gtsam's graph (the anchors' priors, then one between-factor an edge) and initial values;
    also each edge's factor and robust kernel (None where the edge is not robust)."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k, T in initial.items():
        values.insert(k, _to_gtsam(T))
    for k in sorted(anchor_sigmas):
        st, sr = anchor_sigmas[k]
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sr] * 3 + [st] * 3))
        graph.add(gtsam.PriorFactorPose3(k, _to_gtsam(initial[k]), noise))
    factors, kernels = [], []
    for e in edges:
        base = e.noise_model()
        kernel = _kernel(robust_kernel, width) if (robust_kernel is not None and e.robust) else None
        noise = base if kernel is None else gtsam.noiseModel.Robust.Create(kernel, base)
        f = gtsam.BetweenFactorPose3(e.a, e.b, _to_gtsam(e.T_a_b), noise)
        graph.add(f)
        factors.append(f)
        kernels.append(kernel)
    return graph, values, factors, kernels


def _levenberg_marquardt(graph, values, max_iterations: int, relative_error_tol: float,
                         absolute_error_tol: float):
    """gtsam's Levenberg-Marquardt solution of ``graph`` from ``values`` and its iteration
    count; RuntimeError when gtsam fails (e.g. an indeterminant linear system)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    params.setRelativeErrorTol(float(relative_error_tol))
    params.setAbsoluteErrorTol(float(absolute_error_tol))
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    try:
        solution = optimizer.optimize()
    except RuntimeError as exc:  # e.g. gtsam IndeterminantLinearSystemException
        raise RuntimeError(f"pose graph optimisation failed: {exc}") from exc
    return solution, int(optimizer.iterations())


def _edge_residual(i: int, e: RelativePoseEdge, f, kernel, poses: dict[int, np.ndarray], solution,
                   outlier_threshold: float) -> EdgeResidual:
    """Edge ``i``'s residual at the solution (``EdgeResidual``); ``f`` its factor, ``kernel``
    its robust kernel or None."""
    Ta, Tb = poses[e.a], poses[e.b]
    Rm, tm = e.T_a_b[:3, :3], e.T_a_b[:3, 3]
    T_ab = np.linalg.solve(Ta, Tb)
    E_R = Rm.T @ T_ab[:3, :3]
    E_t = Rm.T @ (T_ab[:3, 3] - tm)
    err = np.asarray(f.unwhitenedError(solution), dtype=np.float64)
    wn = e.whitened(err)
    weight = 1.0 if kernel is None else float(kernel.weight(wn))
    return EdgeResidual(
        index=i, a=e.a, b=e.b, kind=e.kind,
        translation_m=float(np.linalg.norm(E_t)), rotation_rad=_rotation_angle(E_R),
        whitened_norm=wn, weight=weight, robust=kernel is not None,
        rejected=kernel is not None and wn > outlier_threshold,
    )
