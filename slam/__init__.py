"""voxfusion SLAM core: sparse-voxel neural implicit RGB-D SLAM (Vox-Fusion++).

Pure tensor maths and state; never imports server/, ar/, fastapi or viser.

The package's face: what the server, the AR layer and a script need, by name, from one place
(``from slam import run_slam, open_sequence, load_config``):

* data: ``open_sequence`` (any layout, or ``synthetic:SPEC``) yields ``Frame``; ``DataError``
* config: ``SLAMConfig``, ``preset``, ``load_config``, ``default_preset_name``; ``ConfigError``
* a run: ``run_slam`` -> ``RunResult`` (``AgentStream`` for a live multi-agent source); its
  events (``PoseEvent`` ... ``FinishedEvent``, the ``Event`` union); ``run.json`` readers
* the map: ``load_checkpoint`` -> ``MapSet``; ``render_view``, ``extract_mesh``
* evaluation: ``ate`` / ``ate_from_pairs`` (aligned ATE), ``mesh_metrics``, TUM trajectories

Names are imported on first use (module ``__getattr__``): ``import slam`` loads neither torch
nor any submodule, so a process that needs one reader pays for that reader only. Everything
else lives in its module (``slam.tracking.Tracker``, ``slam.render``, ``slam.loop``, ...).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS: dict[str, tuple[str, ...]] = {
    "slam.data": ("DataError", "FORMATS", "Frame", "detect_format", "open_sequence"),
    "slam.config": ("ConfigError", "SLAMConfig", "default_preset_name", "load_config", "preset"),
    "slam.runtime": ("AgentStream", "run_slam"),
    "slam.outputs": ("RunResult", "read_run_json", "trajectory_frames", "write_json_atomic"),
    "slam.events": ("Event", "FinishedEvent", "KeyframeEvent", "LoopEvent", "MapUpdateEvent", "PhaseEvent",
                    "PoseEvent", "PosesUpdatedEvent", "StatsEvent", "SubmapEvent"),
    "slam.maps": ("MapSet",),
    "slam.checkpoint": ("CheckpointError", "load_checkpoint", "save_checkpoint"),
    "slam.views": ("render_view",),
    "slam.mesh": ("crop_mesh", "extract_mesh", "mesh_to_bytes"),
    "slam.geometry": ("matrix_to_quat_wxyz", "parse_pose", "quat_wxyz_to_matrix"),
    "slam.eval": ("ATEResult", "MeshMetrics", "Trajectory", "associate", "ate", "ate_from_pairs", "format_tum",
                  "mesh_metrics", "read_tum", "umeyama_alignment", "write_tum"),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_MODULE_OF)


def __getattr__(name: str) -> Any:
    """An exported name, imported from its module on first use (then cached here)."""
    module = _MODULE_OF.get(name)
    if module is None:
        # AttributeError, so that ``from slam import submodule`` goes on to import it.
        raise AttributeError(f"module 'slam' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


if TYPE_CHECKING:  # what the names are, for type checkers and editors; nothing runs here
    from slam.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
    from slam.config import ConfigError, SLAMConfig, default_preset_name, load_config, preset
    from slam.data import FORMATS, DataError, Frame, detect_format, open_sequence
    from slam.eval import (ATEResult, MeshMetrics, Trajectory, associate, ate, ate_from_pairs, format_tum,
                           mesh_metrics, read_tum, umeyama_alignment, write_tum)
    from slam.events import (Event, FinishedEvent, KeyframeEvent, LoopEvent, MapUpdateEvent, PhaseEvent, PoseEvent,
                             PosesUpdatedEvent, StatsEvent, SubmapEvent)
    from slam.geometry import matrix_to_quat_wxyz, parse_pose, quat_wxyz_to_matrix
    from slam.maps import MapSet
    from slam.mesh import crop_mesh, extract_mesh, mesh_to_bytes
    from slam.outputs import RunResult, read_run_json, trajectory_frames, write_json_atomic
    from slam.runtime import AgentStream, run_slam
    from slam.views import render_view
