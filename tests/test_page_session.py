"""The page while a session runs and after it (issue 20), in Debian chromium against a real
uvicorn: the viewer follows the session the page shows and frames it (item 1); the phase with
its own progress, live counts and one frames/s (item 2); the running ATE and the plots
(item 3); AR that says when the object shows, hides or is out of view (item 6); "Use viewer
camera" keeps the render size (item 7).

One synthetic session is started through the page's demo form and watched while it runs (the
``watched`` fixture); the tests then read what was seen and use the finished session."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Iterator

import httpx
import numpy as np
import pytest

from tests.live_server import start_uvicorn
from tests.test_browser import CHROMIUM, CHROMIUM_ARGS
from tests.test_server_api import needs_runtime

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not CHROMIUM.exists(), reason=f"{CHROMIUM} is not installed (scripts/browser-deps.sh)"),
    needs_runtime,
]

FRAMES = 60
"""Long enough that the page is read several times while tracking: under CI's load one read
of the page took seconds (the embedded viewer's software WebGL shares the renderer), and a
24-frame session went by with the page seen only before its first statistics."""
PHASE_ORDER = ["queued", "starting", "tracking", "refining", "writing", "done"]


@dataclass
class Server:
    url: str
    app: object
    api: httpx.Client


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[Server]:
    """The app under a real uvicorn in a thread (the test reads the viewer adapter in-process)."""
    from server.main import create_app
    from server.settings import Settings

    app = create_app(Settings(data_dir=tmp_path_factory.mktemp("page-data"), viewer_port=0, max_sessions=1))
    live = start_uvicorn(app)
    url = live.url
    with httpx.Client(base_url=url, timeout=60) as api:
        yield Server(url, app, api)
    live.stop()


@pytest.fixture(scope="module")
def page(server) -> Iterator[object]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        page.errors = []
        page.on("pageerror", lambda error: page.errors.append(str(error)))
        page.goto(server.url + "/")
        yield page
        browser.close()


@dataclass
class Watched:
    """What the page showed while the session it started ran."""

    session_id: str
    viewer_followed: bool = False
    """The viewer showed the new session while it ran."""
    phases: list[str] = field(default_factory=list)
    live_keyframes: int = 0
    """Largest keyframe count the page showed before the session was done."""
    running_ate: list[str] = field(default_factory=list)
    """The page's ATE texts while running."""
    bar_while_refining: list[bool] = field(default_factory=list)


def item_text(page, session_id: str, part: str) -> str:
    return page.inner_text(f"#session-list li[data-id='{session_id}'] .{part}")


@pytest.fixture(scope="module")
def watched(server, page) -> Watched:
    """Start a synthetic session with the page's form, then read the page every 0.2 s until it ends."""
    page.select_option("#demo-preset", "test")
    page.fill("#demo-frames", str(FRAMES))
    page.click("#demo-button")
    page.wait_for_function("document.getElementById('demo-message').textContent.includes('created')", timeout=20_000)
    session_id = page.inner_text("#demo-message").split()[1]
    page.wait_for_selector(f"#session-list li[data-id='{session_id}']", timeout=10_000)
    seen = Watched(session_id)
    # Bounded, with room for a loaded CI machine (a full-suite run at load 6-12 needed over 120 s).
    deadline = time.monotonic() + 300
    while True:
        assert time.monotonic() < deadline, f"the session did not end; phases seen: {seen.phases}"
        item = page.evaluate(READ_ITEM, session_id)  # one read: the page may update between two
        phase, stats = item["phase"], item["stats"]
        if phase and (not seen.phases or seen.phases[-1] != phase):
            seen.phases.append(phase)
        if phase != "done":
            seen.live_keyframes = max(seen.live_keyframes, int(stats.split(" keyframe")[0].rsplit(" ", 1)[-1]))
            if "ATE" in stats:
                seen.running_ate.append(stats.split("ATE ")[1])
        if phase == "refining":
            seen.bar_while_refining.append(item["bar"])
        if not seen.viewer_followed:
            seen.viewer_followed = server.api.get("/api/viewer").json()["selected"] == session_id
        if phase == "done" and item["finished"]:
            return seen
        time.sleep(0.2)


# The page polls the API once a second on a timer; under load (CI: the SLAM worker, the
# embedded viewer's software WebGL and this process share 2 cores) that timer fell behind for a
# whole 24-frame session, and the page went from "tracking, 1 keyframe" straight to "done".
# Each read therefore asks the page to poll first: what is checked is what the page shows for
# the status the API gives while the session runs, not how often its timer fires.
READ_ITEM = """async (id) => {
    await refreshSessions();
    const li = document.querySelector(`#session-list li[data-id='${id}']`);
    return {phase: li.querySelector('.phase').dataset.phase, stats: li.querySelector('.stats').textContent,
            bar: !li.querySelector('progress').hidden, finished: !!li.querySelector('.badge.finished')};
}"""


def test_the_viewer_follows_the_session_the_page_starts_and_loads(server, page, watched):
    assert watched.viewer_followed, "Start synthetic demo: the viewer shows the new session"
    other = server.api.post("/api/sessions", json={"source": "synthetic", "preset": "test",
                                                   "spec": "orbit?frames=3&width=80&height=60"}).json()["id"]
    page.reload()  # a fresh page targets the newest session: so does the viewer
    page.wait_for_function(f"document.getElementById('render-session').textContent.includes('{other}')",
                           timeout=10_000)
    deadline = time.monotonic() + 10
    while server.api.get("/api/viewer").json()["selected"] != other:
        assert time.monotonic() < deadline, "the viewer did not follow the page's session on a fresh load"
        time.sleep(0.2)
    page.click(f"#session-list li[data-id='{watched.session_id}'] .source")
    deadline = time.monotonic() + 10
    while server.api.get("/api/viewer").json()["selected"] != watched.session_id:
        assert time.monotonic() < deadline, "the viewer did not follow a click in the list"
        time.sleep(0.2)
    server.api.delete(f"/api/sessions/{other}")


def test_a_link_to_a_session_opens_it_rather_than_the_newest(server, page, watched):
    """``/?session=ID`` (what ``voxfusion stream`` prints) shows that session, and the viewer
    follows; an unknown id falls back to the newest."""
    newest = server.api.post("/api/sessions", json={"source": "synthetic", "preset": "test",
                                                    "spec": "orbit?frames=3&width=80&height=60"}).json()["id"]
    try:
        page.goto(f"{server.url}/?session={watched.session_id}")
        page.wait_for_function(f"document.getElementById('render-session').textContent.includes('{watched.session_id}')",
                               timeout=10_000)
        deadline = time.monotonic() + 10
        while server.api.get("/api/viewer").json()["selected"] != watched.session_id:
            assert time.monotonic() < deadline, "the viewer did not follow the linked session"
            time.sleep(0.2)
        page.goto(f"{server.url}/?session=000000000000")
        page.wait_for_function(f"document.getElementById('render-session').textContent.includes('{newest}')",
                               timeout=10_000)
    finally:
        server.api.delete(f"/api/sessions/{newest}")
        page.goto(server.url + "/")


def wait_for_viewer_client(server) -> None:
    deadline = time.monotonic() + 60
    while server.api.get("/api/viewer/camera").status_code != 200:
        assert time.monotonic() < deadline, "the embedded viewer did not connect"
        time.sleep(0.5)


def test_the_viewer_frames_the_session_it_shows(server, page, watched):
    from server.viewer import _scene_bounds, framing

    wait_for_viewer_client(server)
    page.click(f"#session-list li[data-id='{watched.session_id}'] .source")  # shown anew: framed on its bounds now
    viewer = server.app.state.viewer
    deadline = time.monotonic() + 25
    while True:
        camera = viewer.current_camera()
        with viewer._lock:
            bounds = _scene_bounds(viewer._sessions[watched.session_id])
        if camera is not None and bounds is not None:
            position, _ = framing(*bounds, camera.fov_y)
            if np.linalg.norm(camera.T_world_cam[:3, 3] - position) < 0.05:
                break
        assert time.monotonic() < deadline, f"the browser's camera is not framed on the session: {camera} {bounds}"
        time.sleep(0.5)
    centre = (bounds[0] + bounds[1]) / 2
    forward = camera.T_world_cam[:3, 2]
    to_centre = (centre - camera.T_world_cam[:3, 3]) / np.linalg.norm(centre - camera.T_world_cam[:3, 3])
    assert forward @ to_centre > 0.99, "the camera looks at the middle of the session"


def test_the_page_shows_each_phase_with_live_counts(server, watched):
    order = [PHASE_ORDER.index(p) for p in watched.phases]
    assert order == sorted(order) and watched.phases[-1] == "done", watched.phases
    assert "tracking" in watched.phases, watched.phases
    assert watched.live_keyframes > 0, "keyframes are counted while the session runs, not at the end"
    assert all(watched.bar_while_refining), "refining shows its own (running) progress bar"
    state = server.api.get(f"/api/sessions/{watched.session_id}").json()
    assert state["phase"] == "done" and state["phase_elapsed_s"] is None and state["keyframes"] > 0


def test_one_frames_per_second_for_the_page_the_viewer_and_the_plot(server, page, watched):
    state = server.api.get(f"/api/sessions/{watched.session_id}").json()
    stats = item_text(page, watched.session_id, "stats")
    assert f"{state['fps']:.1f} frames/s" in stats
    viewer = server.app.state.viewer
    deadline = time.monotonic() + 10
    while f"{state['fps']:.1f} frames/s" not in viewer.status_line():
        assert time.monotonic() < deadline, (viewer.status_line(), state["fps"])
        time.sleep(0.2)
    series = server.api.get(f"/api/sessions/{watched.session_id}/series").json()
    assert series["fps_frames"][-1] == state["frames_done"] == FRAMES
    assert series["fps_frames"][-1] / series["fps_time_s"][-1] == pytest.approx(state["fps"], rel=0.02)


def test_running_ate_and_plots_of_a_finished_session(server, page, watched):
    assert watched.running_ate and all(text.endswith("so far") for text in watched.running_ate), watched.running_ate
    state = server.api.get(f"/api/sessions/{watched.session_id}").json()
    series = server.api.get(f"/api/sessions/{watched.session_id}/series").json()
    assert series["aligned"] and len(series["estimated"]) == len(series["error_m"]) == FRAMES
    assert len(series["ground_truth"]) == FRAMES
    assert series["ate_rmse_m"] == pytest.approx(state["ate_rmse_m"], abs=1e-4), "the plot's error is the status's"
    page.click(f"#session-list li[data-id='{watched.session_id}'] .source")
    page.wait_for_function("document.getElementById('plots-note').textContent.startsWith('ATE')", timeout=10_000)
    assert f"{state['ate_rmse_m'] * 100:.2f} cm" in page.inner_text("#plots-note")
    for plot in ("plot-trajectory", "plot-error", "plot-fps"):
        drawn = page.evaluate(f"""(() => {{
            const c = document.getElementById('{plot}');
            const data = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            let n = 0;
            for (let i = 3; i < data.length; i += 4) if (data[i] > 0) n++;
            return n / (c.width * c.height);
        }})()""")
        assert drawn > 0.02, f"{plot} is blank ({drawn:.3f} of it drawn)"
    assert not page.errors, page.errors


def test_use_viewer_camera_keeps_the_render_size(server, page, watched):
    wait_for_viewer_client(server)
    page.fill("#cam-width", "200")
    page.fill("#cam-height", "100")
    page.click("#use-viewer-camera")
    page.wait_for_function("document.getElementById('render-message').textContent.includes('viewer')",
                           timeout=10_000)
    assert (page.input_value("#cam-width"), page.input_value("#cam-height")) == ("200", "100")
    page.fill("#cam-width", "320")
    page.fill("#cam-height", "240")


def ar_message(page) -> str:
    page.click("#ar-button")
    page.wait_for_function("!document.getElementById('ar-message').textContent.startsWith('Compositing')",
                           timeout=60_000)
    return page.inner_text("#ar-message")


def test_ar_places_the_default_object_in_view_and_says_when_it_is_not(server, page, watched):
    page.click(f"#session-list li[data-id='{watched.session_id}'] .source")
    page.click("#use-last-pose")
    page.wait_for_function("document.getElementById('render-message').textContent.startsWith('Pose')",
                           timeout=10_000)
    page.select_option("#ar-background", "render")
    for field_id in ("#ar-x", "#ar-y", "#ar-z"):
        page.fill(field_id, "")
    shown = ar_message(page)
    assert shown.startswith("Done: the cube shows"), shown
    for field_id, value in (("#ar-x", "40"), ("#ar-y", "40"), ("#ar-z", "40")):
        page.fill(field_id, value)
    outside = ar_message(page)
    assert "outside the camera's view" in outside, outside
    assert "warn" in page.get_attribute("#ar-message", "class")
    assert page.evaluate("document.getElementById('ar-image').naturalWidth") > 0
    assert not page.errors, page.errors


@pytest.mark.parametrize("size", [(1280, 720), (1400, 900)])
def test_render_and_ar_results_are_in_view_without_scrolling(server, page, watched, size):
    """Issue 20: at 1280x720 and 1400x900 the rendered views, the AR composite and both
    messages sit inside the window as the page loads, so a result is never below the fold."""
    page.click(f"#session-list li[data-id='{watched.session_id}'] .source")
    page.click("#render-button")
    page.wait_for_function("document.getElementById('render-message').textContent.startsWith('Rendered')",
                           timeout=60_000)
    if not page.evaluate("document.getElementById('ar-image').naturalWidth"):
        ar_message(page)
    page.set_viewport_size({"width": size[0], "height": size[1]})
    try:
        page.evaluate("window.scrollTo(0, 0)")
        for element in ("#render-color", "#render-depth", "#render-message", "#ar-image", "#ar-message"):
            box = page.locator(element).bounding_box()
            assert box is not None and box["height"] > 0, f"{element} is not shown"
            assert box["y"] >= 0 and box["y"] + box["height"] <= size[1], f"{element} ends at {box['y'] + box['height']:.0f} px"
            assert box["x"] >= 0 and box["x"] + box["width"] <= size[0], f"{element} is cut off at the side"
    finally:
        page.set_viewport_size({"width": 1280, "height": 720})


def test_ar_response_names_each_objects_visibility(server, watched):
    import json

    import cv2

    from tests.test_server_api import first_pose_camera

    camera = first_pose_camera(server.api, watched.session_id, width=160, height=120, f=120.0)
    T = np.array(camera["T_world_cam"])
    render = server.api.post(f"/api/sessions/{watched.session_id}/render?output=depth", json=camera)
    depth = cv2.imdecode(np.frombuffer(render.content, np.uint8), cv2.IMREAD_UNCHANGED).astype(float) / 1000
    centre_depth = float(np.median(depth[48:72, 64:96][depth[48:72, 64:96] > 0]))  # the server's window
    # A cube far behind the surface, seen through a 12x12 block of pixels that all have depth.
    v, u = next((v, u) for v in range(30, 90, 4) for u in range(40, 120, 4) if (depth[v:v + 12, u:u + 12] > 0).all())
    ray = T[:3, :3] @ np.array([(u + 5.5 - 80) / 120.0, (v + 5.5 - 60) / 120.0, 1.0])  # z = 1: depth along it
    behind = np.eye(4)
    behind[:3, 3] = T[:3, 3] + (float(depth[v:v + 12, u:u + 12].max()) + 20.0) * ray  # about 5 px across
    away = np.eye(4)
    away[:3, 3] = T[:3, 3] - 3.0 * T[:3, 2]  # behind the camera
    objects = [{"shape": "cube", "scale": 0.2},
               {"shape": "cube", "scale": 1.0, "T_world_obj": behind.tolist()},
               {"shape": "sphere", "scale": 0.2, "T_world_obj": away.tolist()}]
    response = server.api.post(f"/api/sessions/{watched.session_id}/ar",
                               json={"background": "render", **camera, "objects": objects})
    assert response.status_code == 200, response.text
    report = json.loads(response.headers["X-AR-Objects"])
    assert [entry["state"] for entry in report] == ["visible", "hidden", "outside"], report
    placed = np.array(report[0]["position"])
    ahead = (placed - T[:3, 3]) @ T[:3, 2]
    assert 0 < ahead < centre_depth, "the default object sits on the optical axis, before the surface"
    assert np.linalg.norm(np.cross(placed - T[:3, 3], T[:3, 2])) < 1e-3
