"""Each browser's own view of the 3D viewer (issue 44 item 4): the plain per-browser state
(``server.viewer_views``) and, with real viser and two WebSocket clients standing in for
browsers, that one browser's choices change its own scene and panel only."""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from server.viewer_views import SHARED_VISIBLE, ClientView, Shadows, shadows
from tests.test_server_viewer import box_mesh, mesh_event, pose_event

# -- the plain state ---------------------------------------------------------------------------


def test_defaults_need_no_shadow_frame():
    view = ClientView()
    assert view.layers == SHARED_VISIBLE and view.shown("s1") == "s1"
    assert shadows(view, "s1", {"s1", "s2"}).frames == {}


def test_a_hidden_layer_and_a_shown_one_are_frames_of_their_own():
    view = ClientView().with_layer("meshes", False).with_layer("regions", True)
    assert shadows(view, "s1", {"s1"}).frames == {"/sessions/s1/meshes": False, "/sessions/s1/regions": True}


def test_colour_by_map_swaps_in_the_shared_variants():
    view = replace(ClientView(), tint_by_map=True, trajectory_by_map=True)
    assert shadows(view, "s1", {"s1"}).frames == {
        "/sessions/s1/meshes": False, "/sessions/s1/tinted": True,
        "/sessions/s1/trajectory": False, "/sessions/s1/trajectory_maps": True}
    # a neural surface hides both mesh variants
    neural = view.with_surface("neural depth")
    assert shadows(neural, "s1", {"s1"}).frames["/sessions/s1/meshes"] is False
    assert "/sessions/s1/tinted" not in shadows(neural, "s1", {"s1"}).frames
    with pytest.raises(ValueError, match="surface"):
        view.with_surface("wireframe")
    with pytest.raises(ValueError, match="layer"):
        view.with_layer("clouds", True)


def test_hidden_maps_in_every_map_layer_seen():
    view = ClientView().with_map(2, False).with_layer("keyframes", False)
    frames = shadows(view, "s1", {"s1"}).frames
    assert frames == {"/sessions/s1/keyframes": False, "/sessions/s1/meshes/map_2": False}, \
        "nothing under a hidden layer (keyframes), nothing in layers not seen (tinted, regions)"
    assert shadows(view.with_map(2, True), "s1", {"s1"}).frames == {"/sessions/s1/keyframes": False}


def test_an_own_session_shadows_both_roots_and_the_page_puts_it_back():
    view = ClientView().with_map(1, False).with_session("s2", "s1")
    assert view.session == "s2" and view.hidden_maps == frozenset(), "another session's maps are other maps"
    assert shadows(view, "s1", {"s1", "s2"}).frames == {"/sessions/s2": True, "/sessions/s1": False}
    assert view.with_session("s1", "s1").session is None, "picking the page's session follows the page again"
    assert shadows(view, "s1", {"s1"}).frames == {}, "a session the viewer does not have: nothing"
    assert view.page_moved() == view and ClientView().with_map(1, False).page_moved().hidden_maps == frozenset()


def test_changes_remove_deepest_first_and_add_parents_first():
    have = {"/sessions/s1/meshes/map_2": False, "/sessions/s1/regions": True}
    want = Shadows({"/sessions/s2": True, "/sessions/s2/regions": True, "/sessions/s1": False})
    remove, add = want.changes(have)
    assert remove == ["/sessions/s1/meshes/map_2", "/sessions/s1/regions"]
    assert list(add) == ["/sessions/s2", "/sessions/s1", "/sessions/s2/regions"]


# -- two browsers on a real viser ---------------------------------------------------------------


class FakeBrowser:
    """A WebSocket client on viser's port, as the API's relay would connect: it reports a camera
    (viser counts a client as connected from its first one) and reads and drops what viser sends,
    so that viser never waits on it."""

    def __init__(self, adapter) -> None:
        import msgspec
        import viser
        from websockets.sync.client import connect

        from server.viewer import RELAY_HEADER

        self.socket = connect(f"ws://127.0.0.1:{adapter.port}", subprotocols=[f"viser-v{viser.__version__}"],
                              additional_headers={RELAY_HEADER: adapter.relay_secret}, max_size=None)
        camera = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0, 0, 0], "position": [0.0, 0, -3], "fov": 1.0,
                  "near": 0.01, "far": 100.0, "image_height": 300, "image_width": 400, "look_at": [0.0, 0, 0],
                  "up_direction": [0.0, -1, 0]}
        self.socket.send(msgspec.msgpack.encode(camera))
        self.thread = threading.Thread(target=self._drain, daemon=True)
        self.thread.start()

    def _drain(self) -> None:
        try:
            while True:
                self.socket.recv()
        except Exception:  # noqa: BLE001 - closed
            return

    def close(self) -> None:
        self.socket.close()


@pytest.fixture()
def two_browsers():
    from server.viewer import ViewerAdapter

    adapter = ViewerAdapter("127.0.0.1", 0)
    adapter.start()
    browsers = [FakeBrowser(adapter) for _ in range(2)]
    deadline = time.monotonic() + 10
    while len(adapter.views()) < 2:
        assert time.monotonic() < deadline, "the two clients did not get panels"
        time.sleep(0.05)
    yield adapter
    for browser in browsers:
        browser.close()
    adapter.stop()


def add_session(adapter, session_id: str, maps: int = 1) -> None:
    for m in range(maps):
        T = np.eye(4)
        T[0, 3] = 3.0 * m
        adapter.handle_event(session_id, pose_event(m, map_id=m))
        event = mesh_event(box_mesh(), T, m + 1)
        adapter.handle_event(session_id, replace(event, map_id=m))
    adapter.flush(force=True)


def test_one_browsers_choices_change_its_own_scene_only(two_browsers):
    adapter = two_browsers
    add_session(adapter, "aaaaaaaaaaaa", maps=2)
    first, second = sorted(adapter.views())
    panel = adapter._panels[first]
    adapter.change(panel, lambda view, _: replace(view.with_layer("trajectory", False), tint_by_map=True))
    adapter.change(panel, lambda view, _: view.with_map(1, False))
    adapter.flush(force=True)
    root = "/sessions/aaaaaaaaaaaa"
    assert adapter.shadow_frames(first) == {f"{root}/meshes": False, f"{root}/tinted": True,
                                            f"{root}/trajectory": False, f"{root}/tinted/map_1": False,
                                            f"{root}/keyframes/map_1": False}
    assert adapter.shadow_frames(second) == {}
    assert adapter.views()[second] == ClientView()
    # the map-coloured meshes are shared: written once, to every browser, hidden but for the first
    assert f"{root}/tinted/map_1" in adapter.nodes and not adapter.nodes[f"{root}/tinted"].visible
    assert adapter.nodes[f"{root}/meshes"].visible, "the shared layer is untouched"
    # the second browser's panel still offers map 1 ticked
    assert adapter._panels[second]._map_boxes[1].value and not panel._map_boxes[1].value


def test_a_browsers_own_session_and_the_pages(two_browsers):
    adapter = two_browsers
    add_session(adapter, "aaaaaaaaaaaa")
    add_session(adapter, "bbbbbbbbbbbb")
    assert adapter.selected == "bbbbbbbbbbbb", "the newest session is the page's until the page picks"
    first, second = sorted(adapter.views())
    adapter.change(adapter._panels[first], lambda view, selected: view.with_session("aaaaaaaaaaaa", selected))
    adapter.flush(force=True)
    assert adapter.shadow_frames(first) == {"/sessions/aaaaaaaaaaaa": True, "/sessions/bbbbbbbbbbbb": False}
    assert adapter._panels[first].session.value == "aaaaaaaaaaaa"
    assert adapter._panels[second].session.value == "bbbbbbbbbbbb"
    assert "the page shows bbbbbbbbbbbb" in adapter._panels[first].status.content
    adapter.select("aaaaaaaaaaaa")  # the page picks: the second browser follows, the first is in step
    adapter.flush(force=True)
    assert adapter._panels[second].session.value == "aaaaaaaaaaaa"
    assert adapter.shadow_frames(first) == {} and adapter.shadow_frames(second) == {}
    adapter.remove_session("bbbbbbbbbbbb")
    adapter.flush(force=True)
    assert adapter._panels[first].session.options == ("aaaaaaaaaaaa",)


# -- the crop box (issue 44 item 11) ------------------------------------------------------------


def test_a_crop_box_keeps_inside_chunks_hides_outside_ones_and_cuts_the_rest():
    from server.viewer_crop import CropBox, crop_chunk
    from server.viewer_state import mesh_chunks

    mesh = box_mesh(2.5)  # 2.5 x 2.5 x 1 around the origin: chunks from -2 to 2 in x and y
    chunks = mesh_chunks(mesh.vertices, mesh.faces, None)
    T = np.eye(4)
    T[0, 3] = 10.0  # the map sits 10 m along x in the world
    box = CropBox.of((9.3, -5, -5), (20, 5, 5))  # world x >= 9.3: map x >= -0.7 (vertices every 0.625)
    kinds = {key: crop_chunk(box, T, chunk) for key, chunk in chunks.items()}
    assert {key for key, part in kinds.items() if part is True} == {key for key in chunks if key[0] >= 0}
    assert {key for key, part in kinds.items() if part is None} == {key for key in chunks if key[0] <= -2}
    cut = [part for part in kinds.values() if part is not None and part is not True]
    assert cut and all((part.vertices[:, 0] >= -0.7).all() for part in cut)
    with pytest.raises(ValueError, match="below its max"):
        CropBox.of((0, 0, 0), (1, 0, 1))
    assert box.query() == "9.3,-5,-5,20,5,5"


def test_a_crop_box_shadows_the_chunks_of_the_mesh_layer_seen():
    from server.viewer_state import mesh_chunks

    mesh = box_mesh(2.5)
    chunks = mesh_chunks(mesh.vertices, mesh.faces, None)
    view = ClientView().with_crop(True, (-0.7, -5, -5), (5, 5, 5))
    result = shadows(view, "s1", {"s1"}, {0: (np.eye(4), chunks)})
    assert result.frames and all(p.startswith("/sessions/s1/meshes/map_0/c_m2") for p in result.frames)
    assert result.meshes and all("/meshes/map_0/c_m1_" in p for p in result.meshes)
    assert shadows(view, "s1", {"s1"}, {0: (np.eye(4), chunks)}).tokens() == result.tokens(), "stable"
    tinted = shadows(replace(view, tint_by_map=True), "s1", {"s1"}, {0: (np.eye(4), chunks)})
    assert all("/tinted/" in p for p in tinted.meshes) and all(m.color is not None for m in tinted.meshes.values())
    assert ClientView().with_crop(False, (0, 0, 0), (1, 1, 1)).crop is None


def test_one_browsers_crop_box_is_its_own_and_the_apis(two_browsers):
    adapter = two_browsers
    add_session(adapter, "aaaaaaaaaaaa")
    first, second = sorted(adapter.views())
    panel = adapter._panels[first]
    assert adapter.current_crop() is None
    adapter.fit_crop(panel)  # fields around the session; cropping is still off
    assert adapter.views()[first].crop is None and panel.crop_min.value[0] < -1.2
    panel.crop_min.value = (0.0, -5.0, -5.0)
    adapter.change(panel, panel.crop_update)
    assert adapter.views()[first].crop is None, "not ticked yet"
    panel.crop_on.value = True
    adapter.change(panel, panel.crop_update)
    adapter.flush(force=True)
    box = adapter.views()[first].crop
    assert box is not None and box.lo == (0.0, -5.0, -5.0)
    assert adapter.current_crop() == box
    from fastapi import HTTPException

    from server.routes_render import viewer_crop

    assert viewer_crop(viewer=adapter).min == (0.0, -5.0, -5.0), "GET /api/viewer/crop"
    with pytest.raises(HTTPException, match="no browser crops"):
        viewer_crop(viewer=None)
    frames = adapter.shadow_frames(first)
    assert any("/meshes/map_0/c_m" in path for path in frames), "chunks left of x = 0 are hidden or cut"
    assert adapter.shadow_frames(second) == {}
    assert "format=glb&crop=0,-5,-5," in panel.crop_note.content
    panel.crop_max.value = (-1.0, 5.0, 5.0)  # an empty box: refused with a note, the old one kept
    adapter.change(panel, panel.crop_update)
    assert adapter.views()[first].crop == box and "below its max" in panel.crop_note.content
