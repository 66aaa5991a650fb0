"""Evaluation: trajectory error (ATE) and reconstruction metrics, as in the paper's tables.

A pure core (``ate``, ``mesh_metrics``) with no file access, TUM file I/O in ``trajectory``,
and thin command-line handlers in ``commands`` (``voxfusion eval-ate`` / ``eval-mesh``).
"""

from slam.eval.ate import ATEResult, ate, ate_from_pairs, umeyama_alignment
from slam.eval.mesh_metrics import CullCamera, MeshMetrics, cull_to_cameras, mesh_metrics
from slam.eval.trajectory import (
    Trajectory,
    associate,
    format_tum,
    parse_tum,
    read_trajectory,
    read_tum,
    write_tum,
)

__all__ = [
    "ATEResult",
    "CullCamera",
    "MeshMetrics",
    "Trajectory",
    "associate",
    "ate",
    "ate_from_pairs",
    "cull_to_cameras",
    "format_tum",
    "mesh_metrics",
    "parse_tum",
    "read_trajectory",
    "read_tum",
    "umeyama_alignment",
    "write_tum",
]
