"""Pose graph over maps (slam.loop.pose_graph): drift correction, robust loops, gauge."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.loop.pose_graph import (
    PoseNode,
    RelativePoseEdge,
    components,
    optimise_pose_graph,
)

N = 8
SEQ_SIGMAS = (0.02, 0.01)
LOOP_SIGMAS = (0.05, 0.02)


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _rel(Ta, Tb) -> np.ndarray:
    return np.linalg.inv(Ta) @ Tb


# Ground truth: 8 map poses around a 3 m circle, with some tilt and height change.
TRUTH = [
    _pose([0.05 * np.sin(i), 0.03, 2 * np.pi * i / N],
          [3 * np.cos(2 * np.pi * i / N), 3 * np.sin(2 * np.pi * i / N), 0.2 * np.sin(i)])
    for i in range(N)
]
# Per-step drift: ~2 deg of rotation and ~5 cm of translation.
BIAS = _pose([0.01, -0.015, 0.03], [0.04, -0.03, 0.02])


def _chain(truth, keys, biased_measurements=False):
    """Initial guesses accumulated with BIAS; sequential edges exact (or biased)."""
    init = [truth[0]]
    edges = []
    for i in range(len(truth) - 1):
        m = _rel(truth[i], truth[i + 1])
        init.append(init[-1] @ m @ BIAS)
        meas = m @ BIAS if biased_measurements else m
        edges.append(RelativePoseEdge(keys[i], keys[i + 1], meas, *SEQ_SIGMAS, kind="sequential"))
    nodes = [PoseNode(k, T) for k, T in zip(keys, init)]
    return nodes, edges


def _loop(truth, a, b, T=None):
    return RelativePoseEdge(a, b, _rel(truth[a], truth[b]) if T is None else T, *LOOP_SIGMAS, kind="loop")


def _max_pos_err(poses, truth, keys) -> float:
    return max(float(np.linalg.norm(poses[k][:3, 3] - truth[i][:3, 3])) for i, k in enumerate(keys))


def _max_rot_err(poses, truth, keys) -> float:
    return max(float(np.linalg.norm(Rotation.from_matrix(_rel(truth[i], poses[k])[:3, :3]).as_rotvec()))
               for i, k in enumerate(keys))


KEYS = list(range(N))


def test_loop_closes_drifted_chain():
    nodes, edges = _chain(TRUTH, KEYS)
    edges.append(_loop(TRUTH, N - 1, 0))
    start = _max_pos_err({n.key: n.T_world for n in nodes}, TRUTH, KEYS)
    res = optimise_pose_graph(nodes, edges, anchors={0})
    end = _max_pos_err(res.poses, TRUTH, KEYS)
    assert start > 0.5                      # 0.71 m of accumulated drift
    assert end < start / 3 and end < 1e-6   # measurements are exact: truth is the optimum
    assert _max_rot_err(res.poses, TRUTH, KEYS) < 1e-6
    loop = res.residuals[-1]
    assert loop.kind == "loop" and loop.translation_m < 1e-6 and loop.rotation_rad < 1e-6
    assert res.final_error < 1e-9 < res.initial_error
    assert 1 <= res.iterations < 50
    assert res.rejected_edges == ()
    assert set(res.poses) == set(KEYS)
    assert all(T.shape == (4, 4) and T.dtype == np.float64 for T in res.poses.values())


def test_loop_spreads_biased_odometry():
    # Realistic case: the tracking chain itself carries the bias; one loop redistributes it.
    nodes, edges = _chain(TRUTH, KEYS, biased_measurements=True)
    edges.append(_loop(TRUTH, N - 1, 0))
    start = _max_pos_err({n.key: n.T_world for n in nodes}, TRUTH, KEYS)
    res = optimise_pose_graph(nodes, edges, anchors={0}, robust_kernel=None)
    end = _max_pos_err(res.poses, TRUTH, KEYS)
    assert end < start / 3                  # 0.71 m -> 0.13 m
    loop = res.residuals[-1]
    assert loop.translation_m < 0.1 and loop.rotation_rad < 0.1


def _outlier_graph():
    nodes, edges = _chain(TRUTH, KEYS)
    edges += [_loop(TRUTH, 7, 0), _loop(TRUTH, 6, 1), _loop(TRUTH, 5, 2)]
    # Wrong by 2 m and 40 deg.
    err = _pose(np.deg2rad(40) * np.array([0.0, 0.6, 0.8]), [2 / np.sqrt(2), 0.0, 2 / np.sqrt(2)])
    edges.append(_loop(TRUTH, 4, 0, _rel(TRUTH[4], TRUTH[0]) @ err))
    return nodes, edges, len(edges) - 1


@pytest.mark.parametrize("kernel, tol", [("huber", 0.1), ("cauchy", 0.01)])
def test_robust_kernel_rejects_outlier_loop(kernel, tol):
    nodes, edges, bad = _outlier_graph()
    res = optimise_pose_graph(nodes, edges, anchors={0}, robust_kernel=kernel)
    assert _max_pos_err(res.poses, TRUTH, KEYS) < tol      # huber 0.055 m, cauchy 0.004 m
    assert _max_rot_err(res.poses, TRUTH, KEYS) < 0.05
    assert res.rejected_edges == (bad,)
    r = res.residuals[bad]
    assert r.rejected and r.robust and r.weight < 0.05
    assert r.translation_m > 1.5 and r.rotation_rad > np.deg2rad(30)
    assert all(x.weight == 1.0 for x in res.residuals if x.kind == "sequential")


def test_without_kernel_outlier_corrupts_solution():
    nodes, edges, bad = _outlier_graph()
    res = optimise_pose_graph(nodes, edges, anchors={0}, robust_kernel=None)
    assert _max_pos_err(res.poses, TRUTH, KEYS) > 0.5       # 1.34 m
    assert res.rejected_edges == ()
    assert not any(x.robust for x in res.residuals)
    # The outlier is partly absorbed by the correct loops, which now carry large residuals.
    assert max(res.residuals[i].whitened_norm for i in range(bad - 3, bad)) > 4
    robust = optimise_pose_graph(nodes, edges, anchors={0}, robust_kernel="huber")
    assert _max_pos_err(res.poses, TRUTH, KEYS) > 10 * _max_pos_err(robust.poses, TRUTH, KEYS)


def _two_agents():
    truth_b = [_pose([0.0, 0.0, -0.3 * i], [20.0 + i, -5.0, 1.0]) for i in range(4)]
    keys_a, keys_b = [0, 1, 2, 3], [10, 11, 12, 13]
    nodes_a, edges_a = _chain(TRUTH[:4], keys_a)
    nodes_b, edges_b = _chain(truth_b, keys_b)
    return nodes_a + nodes_b, edges_a + edges_b, truth_b, keys_a, keys_b


def test_two_components_each_anchored_stay_separate():
    nodes, edges, truth_b, keys_a, keys_b = _two_agents()
    assert components(nodes, edges) == [set(keys_a), set(keys_b)]
    res = optimise_pose_graph(nodes, edges, anchors={0: (1e-6, 1e-6), 10: (1e-6, 1e-6)})
    assert res.components == (frozenset(keys_a), frozenset(keys_b))
    init = {n.key: n.T_world for n in nodes}
    for k in (0, 10):
        assert np.abs(res.poses[k] - init[k]).max() < 1e-6
    assert _max_pos_err(res.poses, TRUTH[:4], keys_a) < 1e-6
    assert _max_pos_err(res.poses, truth_b, keys_b) < 1e-6
    # Solving one agent alone gives the same poses: the components do not interact.
    alone = optimise_pose_graph([n for n in nodes if n.key < 10], [e for e in edges if e.a < 10], {0})
    for k in keys_a:
        assert np.abs(alone.poses[k] - res.poses[k]).max() < 1e-9


def test_unanchored_component_raises_or_auto_anchors():
    nodes, edges, truth_b, keys_a, keys_b = _two_agents()
    with pytest.raises(ValueError, match=r"no anchor.*\[10, 11, 12, 13\]"):
        optimise_pose_graph(nodes, edges, anchors={0})
    res = optimise_pose_graph(nodes, edges, anchors={0}, auto_anchor=True)
    assert res.auto_anchored == (10,) and res.anchored == (0, 10)
    assert _max_pos_err(res.poses, truth_b, keys_b) < 1e-6
    # A loop between the agents joins them: one anchor is then enough.
    joined = edges + [RelativePoseEdge(3, 10, _rel(TRUTH[3], truth_b[0]), *LOOP_SIGMAS, kind="loop")]
    assert components(nodes, joined) == [set(keys_a) | set(keys_b)]
    optimise_pose_graph(nodes, joined, anchors={0})


def test_anchored_node_does_not_move():
    # Anchor a middle node whose initial guess is drifted: it stays, the rest moves around it.
    nodes, edges = _chain(TRUTH, KEYS)
    edges.append(_loop(TRUTH, N - 1, 0))
    init = {n.key: n.T_world for n in nodes}
    res = optimise_pose_graph(nodes, edges, anchors=[4])
    assert np.abs(res.poses[4] - init[4]).max() < 1e-6
    # Relative poses are the true ones, expressed about the fixed node 4.
    for k in KEYS:
        expected = init[4] @ _rel(TRUTH[4], TRUTH[k])
        assert np.abs(res.poses[k] - expected).max() < 1e-6
    assert np.abs(res.poses[0] - init[0]).max() > 0.1
    # A soft anchor (large sigmas) is only a weak prior and yields to the edges.
    soft = optimise_pose_graph(nodes, edges, anchors={4: (10.0, 1.0), 0: (1e-6, 1e-6)})
    assert np.abs(soft.poses[0] - init[0]).max() < 1e-6
    assert np.abs(soft.poses[4] - init[4]).max() > 0.1


def test_input_validation():
    with pytest.raises(ValueError, match="rigid"):
        PoseNode(0, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="shape"):
        PoseNode(0, np.eye(3))
    with pytest.raises(ValueError, match="self-edge"):
        RelativePoseEdge(1, 1, np.eye(4))
    with pytest.raises(ValueError, match="positive"):
        RelativePoseEdge(0, 1, np.eye(4), sigma_translation_m=0.0)
    nodes = [PoseNode(0, np.eye(4)), PoseNode(1, np.eye(4))]
    with pytest.raises(ValueError, match="unknown node keys"):
        optimise_pose_graph(nodes, [RelativePoseEdge(0, 2, np.eye(4))], {0})
    with pytest.raises(ValueError, match="unknown node keys"):
        optimise_pose_graph(nodes, [RelativePoseEdge(0, 1, np.eye(4))], {5})
    with pytest.raises(ValueError, match="duplicate"):
        optimise_pose_graph(nodes + [PoseNode(1, np.eye(4))], [], {0, 1})
    with pytest.raises(ValueError, match="robust_kernel"):
        optimise_pose_graph(nodes, [RelativePoseEdge(0, 1, np.eye(4))], {0}, robust_kernel="tukey")
    e = RelativePoseEdge(0, 1, np.eye(4), kind="sequential")
    assert e.robust is False and RelativePoseEdge(0, 1, np.eye(4)).robust is True
    assert e.sigmas.tolist() == [0.02] * 3 + [0.05] * 3   # gtsam order: rotation, translation
    assert not e.T_a_b.flags.writeable


def test_sigma_order_rotation_then_translation():
    # Two conflicting edges 0 -> 1: one trusts only its rotation, the other only its
    # translation. The solution must take the rotation of the first and the translation of
    # the second; swapped sigmas (translation first) would give the opposite.
    T_rot = _pose([0.0, 0.0, 0.3], [1.0, 0.0, 0.0])
    T_trans = _pose([0.0, 0.0, -0.3], [0.0, 1.0, 0.0])
    nodes = [PoseNode(0, np.eye(4)), PoseNode(1, np.eye(4))]
    edges = [RelativePoseEdge(0, 1, T_rot, sigma_translation_m=100.0, sigma_rotation_rad=1e-4),
             RelativePoseEdge(0, 1, T_trans, sigma_translation_m=1e-4, sigma_rotation_rad=100.0)]
    res = optimise_pose_graph(nodes, edges, {0}, robust_kernel=None)
    T = res.poses[1]
    assert np.abs(T[:3, :3] - T_rot[:3, :3]).max() < 1e-3
    assert np.abs(T[:3, 3] - T_trans[:3, 3]).max() < 1e-3


def test_a_full_covariance_edge_matches_the_same_sigmas():
    """An edge given as a diagonal covariance (translation first) solves like the same sigmas."""
    import numpy as np

    from slam.loop.pose_graph import PoseNode, RelativePoseEdge, optimise_pose_graph

    T = np.eye(4)
    T[:3, 3] = (1.0, 0.2, 0.0)
    nodes = [PoseNode(0, np.eye(4)), PoseNode(1, np.eye(4))]
    by_sigmas = [RelativePoseEdge(0, 1, T, 0.05, 0.02, kind="sequential")]
    cov = np.diag([0.05 ** 2] * 3 + [0.02 ** 2] * 3)
    by_cov = [RelativePoseEdge(0, 1, T, kind="sequential", covariance=cov)]
    a = optimise_pose_graph(nodes, by_sigmas, [0])
    b = optimise_pose_graph(nodes, by_cov, [0])
    assert np.allclose(a.poses[1], b.poses[1], atol=1e-9)
    assert a.final_error == __import__("pytest").approx(b.final_error, abs=1e-12)
