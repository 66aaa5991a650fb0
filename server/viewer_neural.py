"""Neural views in the 3D viewer (issue 44 item 10): instead of the mesh, each browser can see
the map rendered from its own camera: colour, depth, normals, or colour | depth split down the
middle; each browser chooses its own (``server.viewer_views.ClientView.surface``).

The image is the browser's scene background, sent with its depth so that trajectories,
frusta and loop edges still sit in front of or behind the surface where they should
(``SceneApi.set_background_image``). One worker thread renders; a browser that moves again
before its image is done gets only the newest one. The map is the session's newest ``map.pt``
(the server's map cache), so a running session's view follows its checkpoints.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from server.viewer_crop import CropBox
from server.viewer_state import ViewerCamera
from server.viewer_views import SURFACES

VIEW_WIDTH = 256
"""Pixels across a neural view (0.3-0.4 s a view on the 2-core machine, half a 320x240 page render); the
browser scales it up."""
FAR_M = 150.0
"""Depth sent where the render sees nothing (viser's depth range ends at 167 m)."""


def client_camera(client) -> tuple[float, ViewerCamera] | None:
    """(update time, camera) of a viser client's view, or None before it reports one."""
    import torch

    from slam import quat_wxyz_to_matrix

    camera = client.camera
    try:
        stamp = camera.update_timestamp
        wxyz, position, fov = camera.wxyz, camera.position, camera.fov
        width, height = camera.image_width, camera.image_height
    except AssertionError:  # the client has not reported its camera yet
        return None
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_matrix(torch.as_tensor(np.asarray(wxyz, dtype=np.float64))).numpy()
    T[:3, 3] = position
    return float(stamp), ViewerCamera(T_world_cam=T, fov_y=float(fov), width=int(width), height=int(height))


def neural_image(mapset, camera: ViewerCamera, surface: str, width: int = VIEW_WIDTH,
                 crop: CropBox | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The map seen by ``camera`` as ``surface`` shows it (only what lies inside ``crop``, if
    given): (H, W, 3) uint8 image and (H, W) float32 z-depth in metres (FAR_M where nothing is seen)."""
    from slam.camera_path import normals_from_depth, normals_image
    from slam.path_video import auto_depth_range, depth_image
    from slam.views import render_view

    if surface not in SURFACES[1:]:
        raise ValueError(f"surface must be one of {SURFACES[1:]}, got {surface!r}")
    fx, fy, cx, cy, w, h = camera.intrinsics(width)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    view = render_view(mapset, camera.T_world_cam, K, w, h, crop=None if crop is None else (crop.lo, crop.hi))
    depth = np.where(view.valid, view.depth, 0.0)
    panels = {"neural colour": lambda: np.clip(view.rgb, 0, 1),
              "neural depth": lambda: depth_image(depth, auto_depth_range(depth)),
              "neural normals": lambda: normals_image(normals_from_depth(depth, K))}
    if surface == "colour | depth":
        image = np.concatenate([panels["neural colour"]()[:, : w // 2], panels["neural depth"]()[:, w // 2:]], axis=1)
    else:
        image = panels[surface]()
    return np.round(image * 255).astype(np.uint8), np.where(view.valid, view.depth, FAR_M).astype(np.float32)


@dataclass(frozen=True)
class _Request:
    client: object
    session_id: str
    surface: str
    camera: ViewerCamera
    crop: CropBox | None


@dataclass(frozen=True)
class Wanted:
    """What one browser wants to see behind its scene: a surface of a session (or nothing)."""

    client: object
    session_id: str | None
    surface: str
    crop: CropBox | None = None


class NeuralViews:
    """Per browser, the neural view of the session it shows from its camera (module doc).
    ``map_source(session_id)`` gives the session's map set, or None while it has none."""

    def __init__(self, map_source: Callable[[str], object | None]) -> None:
        self.map_source = map_source
        self._surfaces: dict[int, str] = {}
        """client id -> the surface it wants now (a view of another one is not shown)."""
        self._shown: dict[int, tuple] = {}
        """client id -> (session, surface, camera time) of its newest requested view."""
        self._pending: dict[int, _Request] = {}
        self._wake = threading.Condition()
        self._stopped = False
        self._thread = threading.Thread(target=self._work, name="viewer-neural", daemon=True)
        self._thread.start()
        self.views_rendered = 0

    def update(self, wanted: dict[int, Wanted]) -> None:
        """Ask for a view for every client (id -> what it wants) whose camera, session or surface
        changed (the flusher calls this); a client back on ``mesh`` has its background cleared once."""
        with self._wake:
            self._surfaces = {client_id: want.surface for client_id, want in wanted.items()}
            for client_id, want in wanted.items():
                if want.surface == "mesh" or want.session_id is None:
                    if self._shown.pop(client_id, None) is not None:
                        want.client.scene.set_background_image(None)
                    continue
                seen = client_camera(want.client)
                if seen is None:
                    continue
                key = (want.session_id, want.surface, seen[0], want.crop)
                if self._shown.get(client_id) != key:
                    self._shown[client_id] = key
                    self._pending[client_id] = _Request(want.client, want.session_id, want.surface, seen[1],
                                                        want.crop)
                    self._wake.notify()
            for gone in set(self._shown) - set(wanted):
                self._shown.pop(gone, None)

    def stop(self) -> None:
        with self._wake:
            self._stopped = True
            self._wake.notify()

    def _work(self) -> None:
        while True:
            with self._wake:
                while not self._pending and not self._stopped:
                    self._wake.wait()
                if self._stopped:
                    return
                client_id = next(iter(self._pending))
                request = self._pending.pop(client_id)
            try:
                mapset = self.map_source(request.session_id)
                if mapset is None or request.surface != self._surfaces.get(client_id):
                    continue
                image, depth = neural_image(mapset, request.camera, request.surface, crop=request.crop)
                request.client.scene.set_background_image(image, format="jpeg", depth=depth)
                self.views_rendered += 1
            except Exception:  # noqa: BLE001 - a failed view (a client gone, a bad map) fails alone
                import traceback

                traceback.print_exc()
