"""Loop closures checked against ground truth by the relative pose they measured.

A loop joins a query keyframe to an earlier (match) keyframe with a measured relative pose
``T_match_query`` (``run.json``'s ``loop_closures`` and ``loop_candidates`` record it). Its error
is the difference between that pose and the ground truth's ``T_gt_match^-1 T_gt_query``: a
true loop measures a small error whatever the distance between its frames, a false one does
not, so a loop joining frames 1.2 m and 18 degrees apart can be told right or wrong.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np


@dataclass(frozen=True)
class LoopPoseError:
    """One loop's measured relative pose against the ground truth's."""

    agent: int
    frame_index: int
    match_agent: int
    match_frame_index: int
    translation_m: float
    """|t_measured - t_gt| of the query camera in the match camera's frame."""
    rotation_deg: float
    """Angle of R_measured^T R_gt."""
    gt_distance_m: float
    """How far apart the two cameras are by ground truth."""


def relative_pose_error(T_match_query: np.ndarray, T_world_match_gt: np.ndarray,
                        T_world_query_gt: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between a measured (4, 4) relative pose and the ground truth's.

    Example: a measured identity between two GT poses 0.1 m apart along x -> (0.1, 0.0).
    """
    T_gt = np.linalg.solve(np.asarray(T_world_match_gt, np.float64), np.asarray(T_world_query_gt, np.float64))
    T = np.asarray(T_match_query, np.float64)
    translation = float(np.linalg.norm(T[:3, 3] - T_gt[:3, 3]))
    cos = (np.trace(T[:3, :3].T @ T_gt[:3, :3]) - 1) / 2
    return translation, float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def loop_pose_errors(loops: Iterable[dict],
                     gt_pose: Callable[[int, int], np.ndarray | None]) -> list[LoopPoseError]:
    """The pose error of every loop record that holds ``T_match_query``; ``gt_pose(agent,
    frame_index)`` gives the (4, 4) GT camera-to-world pose or None (the loop is skipped)."""
    errors = []
    for loop in loops:
        measured = loop.get("T_match_query")
        if measured is None:
            continue
        query = gt_pose(loop["agent"], loop["frame_index"])
        match = gt_pose(loop["match_agent"], loop["match_frame_index"])
        if query is None or match is None:
            continue
        translation, rotation = relative_pose_error(np.asarray(measured), match, query)
        errors.append(LoopPoseError(loop["agent"], loop["frame_index"], loop["match_agent"], loop["match_frame_index"],
                                    translation, rotation, float(np.linalg.norm(query[:3, 3] - match[:3, 3]))))
    return errors
