"""The keyframe pose graph (slam.loop.keyframe_graph): a loop bends a drifting trajectory back
inside maps, maps take the rigid pose that fits their keyframes, wrong loops are switched off."""

from __future__ import annotations

import numpy as np
import pytest

from slam.loop.keyframe_graph import (
    KeyframeLoop,
    KeyframeNode,
    MapNode,
    odometry_measurement,
    optimise_keyframe_graph,
    rigid_motion,
)


def pose(yaw: float, x: float, y: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = (x, y, 0.0)
    return T


def circle(n: int, radius: float = 1.5) -> list[np.ndarray]:
    """GT camera poses on a circle, one lap and a bit (the last ones revisit the first)."""
    angles = np.linspace(0, 2 * np.pi * 1.1, n)
    return [pose(a + np.pi / 2, radius * np.cos(a), radius * np.sin(a)) for a in angles]


def drifted(gt: list[np.ndarray], yaw_bias: float) -> list[np.ndarray]:
    """Odometry chained from GT steps with a constant yaw error per step (slow drift)."""
    out = [gt[0]]
    for a, b in zip(gt, gt[1:]):
        out.append(out[-1] @ np.linalg.solve(a, b) @ pose(yaw_bias, 0, 0))
    return out


def split_into_maps(poses: list[np.ndarray], size: int) -> tuple[list[MapNode], list[KeyframeNode]]:
    """Maps of ``size`` keyframes each, placed at their first keyframe, each the parent of the next."""
    maps, keyframes = [], []
    for m, start in enumerate(range(0, len(poses), size)):
        T_world_map = poses[start]
        parent = m - 1 if m else None
        T_parent_map = np.linalg.solve(maps[-1].T_world_map, T_world_map) if m else None
        maps.append(MapNode(m, T_world_map, parent, T_parent_map))
        for i in range(start, min(start + size, len(poses))):
            keyframes.append(KeyframeNode(0, m, i, np.linalg.solve(T_world_map, poses[i])))
    return maps, keyframes


def rmse(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    return float(np.sqrt(np.mean([np.sum((x[:3, 3] - y[:3, 3]) ** 2) for x, y in zip(a, b)])))


def loops_from_gt(gt: list[np.ndarray], pairs: list[tuple[int, int]]) -> list[KeyframeLoop]:
    return [KeyframeLoop(0, q, 0, m, np.linalg.solve(gt[m], gt[q])) for q, m in pairs]


def test_odometry_measurement_follows_the_chain_across_a_region_border():
    gt = circle(12)
    maps, keyframes = split_into_maps(gt, 5)
    by_map = {m.map_id: m for m in maps}
    for a, b in zip(keyframes, keyframes[1:]):
        assert np.allclose(odometry_measurement(a, b, by_map), np.linalg.solve(gt[a.frame_index], gt[b.frame_index]))
    floating = {**by_map, 1: MapNode(1, maps[1].T_world_map)}  # started after a tracking failure
    assert odometry_measurement(keyframes[4], keyframes[5], floating) is None


def test_a_loop_bends_the_drift_out_inside_maps():
    gt = circle(60)
    est = drifted(gt, yaw_bias=0.004)
    maps, keyframes = split_into_maps(est, 20)
    loops = loops_from_gt(gt, [(q, q - 54) for q in range(54, 60)])
    solved = optimise_keyframe_graph(maps, keyframes, loops)
    after = [solved.keyframe_poses[(0, i)] for i in range(60)]
    before_err, after_err = rmse(est, gt), rmse(after, gt)
    assert before_err > 0.05
    assert after_err < 0.35 * before_err, (before_err, after_err)
    assert solved.loops_used == 6 and solved.loops_rejected == 0
    assert solved.keyframe_poses[(0, 0)] == pytest.approx(est[0], abs=1e-6), "the first keyframe is the anchor"
    # Each map moved as the rigid motion that best carries its keyframes; its keyframes'
    # poses in the map express the new world poses under it.
    in_maps = solved.keyframes_in_maps(keyframes)
    for k in keyframes:
        T_world = solved.map_poses[k.map_id] @ in_maps[(0, k.frame_index)]
        assert np.allclose(T_world, solved.keyframe_poses[(0, k.frame_index)], atol=1e-9)
    last = [k for k in keyframes if k.map_id == 2]
    motion = rigid_motion([maps[2].T_world_map @ k.T_map_cam for k in last], [solved.keyframe_poses[(0, k.frame_index)] for k in last])
    assert np.allclose(solved.map_poses[2], motion @ maps[2].T_world_map, atol=1e-9)
    # ...except the world's first map, whose first keyframe anchors the world: it stays put
    # while its other keyframes move (a best fit over them would move the world's origin).
    assert np.array_equal(solved.map_poses[0], maps[0].T_world_map)
    moved = max(np.abs(solved.keyframe_poses[(0, k.frame_index)] - maps[0].T_world_map @ k.T_map_cam).max()
                for k in keyframes if k.map_id == 0)
    assert moved > 1e-3


def test_a_wrong_loop_is_switched_off():
    gt = circle(60)
    est = drifted(gt, yaw_bias=0.004)
    maps, keyframes = split_into_maps(est, 20)
    right = loops_from_gt(gt, [(q, q - 54) for q in range(54, 60)])
    wrong = [KeyframeLoop(0, 40, 0, 5, pose(0.0, 0.3, 0.0))]  # keyframes GT puts 2.5 m apart
    solved = optimise_keyframe_graph(maps, keyframes, right + wrong)
    assert solved.loops_rejected >= 1 and solved.loops_used == 6
    after = [solved.keyframe_poses[(0, i)] for i in range(60)]
    assert rmse(after, gt) < 0.5 * rmse(est, gt)


def test_no_loop_changes_nothing():
    gt = circle(20)
    est = drifted(gt, yaw_bias=0.004)
    maps, keyframes = split_into_maps(est, 8)
    solved = optimise_keyframe_graph(maps, keyframes, [])
    for i in range(20):
        assert np.allclose(solved.keyframe_poses[(0, i)], est[i], atol=1e-6)
    for m in maps:
        assert np.allclose(solved.map_poses[m.map_id], m.T_world_map, atol=1e-6)
    assert solved.max_correction_m < 1e-6


def test_a_second_camera_no_loop_joined_keeps_its_own_anchor():
    gt = circle(20)
    maps, keyframes = split_into_maps(gt, 10)
    other = MapNode(7, pose(0.3, 5.0, 5.0))
    keyframes += [KeyframeNode(1, 7, i, pose(0.0, 0.1 * i, 0.0)) for i in range(5)]
    solved = optimise_keyframe_graph(maps + [other], keyframes, loops_from_gt(gt, [(19, 1)]))
    assert np.allclose(solved.map_poses[7], other.T_world_map, atol=1e-6)


def test_frame_covariance_is_wide_where_the_view_fixes_nothing():
    """A plain wall ahead (normal along z): translation along z is stiff, x and y are not;
    rotation about z is free, about x and y stiff."""
    from slam.loop.keyframe_graph import FRAME_SIGMA_M, FRAME_SIGMA_RAD, MAX_CURVATURE_RATIO, frame_covariance

    H = np.diag([0.05, 0.05, 50.0, 30.0, 30.0, 1e-9])
    C = frame_covariance(H)
    assert C[2, 2] == pytest.approx(FRAME_SIGMA_M ** 2)
    assert C[0, 0] == pytest.approx(FRAME_SIGMA_M ** 2 * 50.0 / 0.05)
    assert C[3, 3] == pytest.approx(FRAME_SIGMA_RAD ** 2)
    assert C[5, 5] == pytest.approx(FRAME_SIGMA_RAD ** 2 * MAX_CURVATURE_RATIO), "capped"
    assert np.allclose(C[:3, 3:], 0) and np.allclose(C, C.T)
    R = pose(0.7, 0, 0)[:3, :3]  # the same wall seen turned: the wide directions turn with it
    H_turned = np.zeros((6, 6))
    H_turned[:3, :3], H_turned[3:, 3:] = R @ H[:3, :3] @ R.T, R @ H[3:, 3:] @ R.T
    assert np.allclose(frame_covariance(H_turned)[:3, :3], R @ C[:3, :3] @ R.T)


def test_the_correction_goes_where_tracking_was_unsure():
    """Drift injected along x in a stretch of keyframes whose covariance says x was not
    observed there: with those covariances the loop puts its correction in that stretch, and
    the trajectory ends closer to the truth than with the distance rule alone."""
    from slam.loop.keyframe_graph import FRAME_SIGMA_M, FRAME_SIGMA_RAD

    gt = circle(60)
    est, sliding = [gt[0]], range(20, 30)
    for i in range(1, 60):
        step = np.linalg.solve(gt[i - 1], gt[i])
        if i in sliding:
            step = step @ pose(0.0, -0.01, 0.0)  # the camera under-tracks along its own x
        est.append(est[-1] @ step)
    maps, keyframes = split_into_maps(est, 60)
    sure = np.diag([FRAME_SIGMA_M ** 2] * 3 + [FRAME_SIGMA_RAD ** 2] * 3)
    unsure = sure.copy()
    unsure[0, 0] *= 1e4
    with_cov = [KeyframeNode(k.agent, k.map_id, k.frame_index, k.T_map_cam,
                             unsure if k.frame_index in sliding else sure) for k in keyframes]
    loops = loops_from_gt(gt, [(q, q - 54) for q in range(54, 60)])
    plain = optimise_keyframe_graph(maps, keyframes, loops)
    informed = optimise_keyframe_graph(maps, with_cov, loops)
    err = {name: rmse([r.keyframe_poses[(0, i)] for i in range(60)], gt) for name, r in
           (("plain", plain), ("informed", informed))}
    assert err["informed"] < 0.5 * err["plain"], err
    assert err["informed"] < 0.01, err
