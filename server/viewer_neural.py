"""Neural views in the 3D viewer: instead of the mesh, each browser can see
the map rendered from its own camera: colour, depth, normals, or colour | depth split down the
middle; each browser chooses its own (``server.viewer_views.ClientView.surface``).

The image is the browser's scene background, sent with its depth so that trajectories,
frusta and loop edges still sit in front of or behind the surface where they should
(``SceneApi.set_background_image``). One worker thread renders; a browser that moves again
before its image is done gets only the newest one. The map is the session's newest ``map.pt``
(the server's map cache), so a running session's view follows its checkpoints.

Views are progressive (the best view within the latency target): a move gets
a ``VIEW_WIDTH`` image at once, and once the camera has rested ``REFINE_AFTER_S`` a sharper one
at the browser's own width (at most ``REFINED_WIDTH``) replaces it. The sharper one is rendered
in bands of rows and dropped between bands as soon as that browser moves again, so a move
waits for one band at most; moves of every browser go before any sharper view.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from server.viewer_crop import CropBox
from server.viewer_state import ViewerCamera
from server.viewer_views import SURFACES

VIEW_WIDTH = 256
"""Pixels across a neural view (0.3-0.4 s a view on the 2-core machine, half a 320x240 page render); the
browser scales it up."""
REFINED_WIDTH = 640
"""Most pixels across the sharper view of a resting camera (a 640x480 view: 0.9 s on the
2-core machine's two threads, 1.4 s on one while a session runs; benchmarks/README.md)."""
REFINE_AFTER_S = 0.3
"""Rest of a camera before its sharper view starts (a camera being dragged reports every
frame, so a drag starts none)."""
REFINE_BANDS = 4
"""Row bands of a sharper view: a move waits for one band, about a quarter of the view."""
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
                 crop: CropBox | None = None, *, bands: int = 1,
                 stale: Callable[[], bool] = lambda: False) -> tuple[np.ndarray, np.ndarray] | None:
    """The map seen by ``camera`` as ``surface`` shows it (only what lies inside ``crop``, if
    given): (H, W, 3) uint8 image and (H, W) float32 z-depth in metres (FAR_M where nothing is seen).

    Rendered in ``bands`` bands of rows (each a view of its own rows, through the same
    camera); None when ``stale()`` turns true between two bands."""
    from slam.camera_path import normals_from_depth, normals_image
    from slam.path_video import auto_depth_range, depth_image

    if surface not in SURFACES[1:]:
        raise ValueError(f"surface must be one of {SURFACES[1:]}, got {surface!r}")
    fx, fy, cx, cy, w, h = camera.intrinsics(width)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    box = None if crop is None else (crop.lo, crop.hi)
    rows = band_starts(h, bands)
    rgb, z, valid = [], [], []
    for top, bottom in zip(rows, rows[1:] + [h]):
        if top > 0 and stale():
            return None
        band = _render_rows(mapset, camera.T_world_cam, K, w, top, bottom, box)
        rgb.append(band.rgb)
        z.append(band.depth)
        valid.append(band.valid)
    rgb, z, valid = np.concatenate(rgb), np.concatenate(z), np.concatenate(valid)
    depth = np.where(valid, z, 0.0)
    panels = {"neural colour": lambda: np.clip(rgb, 0, 1),
              "neural depth": lambda: depth_image(depth, auto_depth_range(depth)),
              "neural normals": lambda: normals_image(normals_from_depth(depth, K))}
    if surface == "colour | depth":
        image = np.concatenate([panels["neural colour"]()[:, : w // 2], panels["neural depth"]()[:, w // 2:]], axis=1)
    else:
        image = panels[surface]()
    return np.round(image * 255).astype(np.uint8), np.where(valid, z, FAR_M).astype(np.float32)


def band_starts(height: int, bands: int) -> list[int]:
    """First rows of ``bands`` bands of a ``height``-row image, each but the last a multiple of
    the banded renderer's coarse stride high (its coarse pass then sees the same pixels)."""
    from slam.views import DEFAULT_COARSE_STRIDE as stride

    rows = -(-height // max(1, bands))
    rows = max(stride, -(-rows // stride) * stride)
    return list(range(0, height, rows))


def _render_rows(mapset, T_world_cam, K: np.ndarray, width: int, top: int, bottom: int, box):
    """Rows ``top`` to ``bottom`` (excluded) of a ``width``-wide view: the same camera with
    its principal point moved up by ``top``."""
    from slam.views import render_view

    K_rows = K.copy()
    K_rows[1, 2] -= top
    return render_view(mapset, T_world_cam, K_rows, width, bottom - top, crop=box)


@dataclass(frozen=True)
class _Request:
    client: object
    session_id: str
    surface: str
    camera: ViewerCamera
    crop: CropBox | None
    key: tuple
    """(session, surface, camera time, crop) the request was made for."""


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

    def __init__(self, map_source: Callable[[str], object | None], *, refined_width: int = REFINED_WIDTH,
                 refine_after_s: float = REFINE_AFTER_S) -> None:
        self.map_source = map_source
        self.refined_width = refined_width
        self.refine_after_s = refine_after_s
        self._surfaces: dict[int, str] = {}
        """client id -> the surface it wants now (a view of another one is not shown)."""
        self._shown: dict[int, tuple] = {}
        """client id -> (session, surface, camera time, crop) of its newest requested view."""
        self._pending: dict[int, _Request] = {}
        """client id -> the view its newest move asks for (first in line)."""
        self._refine: dict[int, tuple[float, _Request]] = {}
        """client id -> (when it may start, request) of the sharper view of its resting camera."""
        self._wake = threading.Condition()
        self._stopped = False
        self._thread = threading.Thread(target=self._work, name="viewer-neural", daemon=True)
        self._thread.start()
        self.views_rendered = 0
        self.views_refined = 0

    def update(self, wanted: dict[int, Wanted]) -> None:
        """Ask for a view for every client (id -> what it wants) whose camera, session or surface
        changed (the flusher calls this); a client back on ``mesh`` has its background cleared once."""
        with self._wake:
            self._surfaces = {client_id: want.surface for client_id, want in wanted.items()}
            for client_id, want in wanted.items():
                if want.surface == "mesh" or want.session_id is None:
                    self._refine.pop(client_id, None)
                    if self._shown.pop(client_id, None) is not None:
                        want.client.scene.set_background_image(None)
                    continue
                seen = client_camera(want.client)
                if seen is None:
                    continue
                key = (want.session_id, want.surface, seen[0], want.crop)
                if self._shown.get(client_id) != key:
                    self._shown[client_id] = key
                    self._refine.pop(client_id, None)
                    self._pending[client_id] = _Request(want.client, want.session_id, want.surface, seen[1],
                                                        want.crop, key)
                    self._wake.notify()
            for gone in set(self._shown) - set(wanted):
                self._shown.pop(gone, None)
                self._refine.pop(gone, None)

    def stop(self) -> None:
        with self._wake:
            self._stopped = True
            self._wake.notify()

    def _next(self) -> tuple[int, _Request, bool] | None:
        """(client id, request, whether it is a sharper view) to render next; None: stopped.
        Waits for a move, or for a resting camera's sharper view to fall due."""
        with self._wake:
            while not self._stopped:
                if self._pending:
                    client_id = next(iter(self._pending))
                    return client_id, self._pending.pop(client_id), False
                now = time.monotonic()
                due = min(self._refine.items(), key=lambda item: item[1][0], default=None)
                if due is not None and due[1][0] <= now:
                    del self._refine[due[0]]
                    return due[0], due[1][1], True
                self._wake.wait(None if due is None else due[1][0] - now)
            return None

    def _is_stale(self, client_id: int, request: _Request) -> bool:
        """Whether the client has moved (or changed what it shows) since ``request``."""
        with self._wake:
            return client_id in self._pending or self._shown.get(client_id) != request.key

    def _work(self) -> None:
        while (item := self._next()) is not None:
            client_id, request, sharper = item
            try:
                mapset = self.map_source(request.session_id)
                if mapset is None or request.surface != self._surfaces.get(client_id):
                    continue
                if sharper:
                    self._render_sharper(client_id, request, mapset)
                    continue
                image, depth = neural_image(mapset, request.camera, request.surface, crop=request.crop)
                request.client.scene.set_background_image(image, format="jpeg", depth=depth)
                self.views_rendered += 1
                if self._sharper_width(request) > VIEW_WIDTH:
                    with self._wake:
                        if not self._is_stale(client_id, request):
                            self._refine[client_id] = (time.monotonic() + self.refine_after_s, request)
            except Exception:  # noqa: BLE001 - a failed view (a client gone, a bad map) fails alone
                import traceback

                traceback.print_exc()

    def _sharper_width(self, request: _Request) -> int:
        """Pixels across the sharper view: the browser's own width, at most ``refined_width``."""
        return min(request.camera.width, self.refined_width)

    def _render_sharper(self, client_id: int, request: _Request, mapset) -> None:
        """The resting camera's sharper view, in bands, dropped when the client moves meanwhile."""
        shown = neural_image(mapset, request.camera, request.surface, self._sharper_width(request), request.crop,
                             bands=REFINE_BANDS, stale=lambda: self._is_stale(client_id, request))
        if shown is None or self._is_stale(client_id, request):
            return
        request.client.scene.set_background_image(shown[0], format="jpeg", depth=shown[1])
        self.views_refined += 1
