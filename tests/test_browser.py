"""The page in a real browser (Debian chromium driven by playwright) against a real uvicorn:
it loads, an upload works (listed with its file name, and the viewer follows it), the embedded
viewer connects and shows the mesh, the render panel returns an image."""

from __future__ import annotations

import io
import time
import zipfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import cv2
import httpx
import numpy as np
import pytest

from tests.live_server import start_uvicorn

from tests.test_server_api import needs_runtime

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--disable-background-networking"]

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not CHROMIUM.exists(), reason=f"{CHROMIUM} is not installed (scripts/browser-deps.sh)"),
    needs_runtime,
]


@pytest.fixture(scope="module")
def server_url(tmp_path_factory) -> Iterator[str]:
    """The app under a real uvicorn (the viewer's WebSocket needs a real server) in a thread."""
    from server.main import create_app
    from server.settings import Settings

    settings = Settings(data_dir=tmp_path_factory.mktemp("browser-data"), viewer_port=0, max_sessions=2)
    live = start_uvicorn(create_app(settings))
    yield live.url
    live.stop()


def tum_zip_of_synthetic_frames(frames: int = 8) -> bytes:
    """A TUM RGB-D layout (rgb.txt, depth.txt, intrinsics.txt, 16-bit depth at 5000/m) in a zip."""
    from slam.data import open_sequence

    sequence = open_sequence(f"synthetic:orbit?frames={frames}&width=160&height=120")
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        rgb_list, depth_list = ["# color images"], ["# depth images"]
        for frame in sequence:
            stamp = f"{100.0 + frame.timestamp:.6f}"
            bgr = cv2.cvtColor(np.round(frame.rgb * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
            archive.writestr(f"room/rgb/{stamp}.png", cv2.imencode(".png", bgr)[1].tobytes())
            depth = np.round(frame.depth * 5000).astype(np.uint16)
            archive.writestr(f"room/depth/{stamp}.png", cv2.imencode(".png", depth)[1].tobytes())
            rgb_list.append(f"{stamp} rgb/{stamp}.png")
            depth_list.append(f"{stamp} depth/{stamp}.png")
        K = sequence[0].K
        archive.writestr("room/rgb.txt", "\n".join(rgb_list) + "\n")
        archive.writestr("room/depth.txt", "\n".join(depth_list) + "\n")
        archive.writestr("room/intrinsics.txt", f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    return buffer.getvalue()


def non_background_fraction(png: bytes) -> float:
    """Share of pixels in the middle of the viewer that are not viser's white background
    (left of its GUI panel, below its notifications): the mesh fills it, lines alone do not."""
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    h, w = image.shape[:2]
    middle = image[int(0.4 * h): int(0.9 * h), int(0.35 * w): int(0.65 * w)]
    return float((middle.min(axis=2) < 235).mean())


def test_page_upload_viewer_and_render(server_url, tmp_path):
    from playwright.sync_api import sync_playwright

    api = httpx.Client(base_url=server_url, timeout=30)
    session_id = api.post("/api/sessions", json={"source": "synthetic", "preset": "test",
                                                 "spec": "orbit?frames=12&width=160&height=120"}).json()["id"]
    deadline = time.monotonic() + 150
    while api.get(f"/api/sessions/{session_id}").json()["status"] != "finished":
        assert time.monotonic() < deadline, "synthetic session did not finish"
        time.sleep(0.5)
    zip_path = tmp_path / "room.zip"
    zip_path.write_bytes(tum_zip_of_synthetic_frames())

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(server_url + "/")
        assert page.title().startswith("voxfusion")
        page.wait_for_selector(f"#session-list li[data-id='{session_id}'] .badge.finished", timeout=20_000)
        stats = page.inner_text(f"#session-list li[data-id='{session_id}'] .stats")
        assert "map" in stats and "loop" in stats and "1 agent" in stats, stats

        # Upload a dataset zip through the form (XMLHttpRequest with a progress bar).
        page.set_input_files("#upload-file", str(zip_path))
        page.select_option("#upload-preset", "test")
        page.click("#upload-button")
        page.wait_for_function("document.getElementById('upload-message').textContent.includes('created')",
                               timeout=60_000)
        uploaded = [s for s in api.get("/api/sessions").json() if s["source"].startswith("upload")]
        assert len(uploaded) == 1, uploaded
        item = f"#session-list li[data-id='{uploaded[0]['id']}']"
        page.wait_for_selector(item, timeout=10_000)
        assert "room.zip" in page.inner_text(f"{item} .source"), "an upload is listed with its file name"
        deadline = time.monotonic() + 10
        while api.get("/api/viewer").json()["selected"] != uploaded[0]["id"]:
            assert time.monotonic() < deadline, "the viewer did not follow the uploaded session"
            time.sleep(0.2)
        api.post(f"/api/sessions/{uploaded[0]['id']}/cancel")  # frees the CPU for the browser's software WebGL

        # Show the finished synthetic session in the viewer; the viewer connects and draws its mesh.
        page.click(f"#session-list li[data-id='{session_id}'] .source")
        deadline = time.monotonic() + 90
        while api.get("/api/viewer").json()["clients"] < 1:
            assert time.monotonic() < deadline, "the embedded viewer did not connect"
            time.sleep(0.5)
        viewer = page.locator("#viewer-frame")
        fraction = 0.0
        while fraction < 0.08:
            assert time.monotonic() < deadline, f"no mesh in the viewer ({fraction:.3f} of it is not background; " \
                                                f"see {tmp_path / 'viewer.png'})"
            time.sleep(2.0)
            shot = viewer.screenshot(timeout=60_000)
            (tmp_path / "viewer.png").write_bytes(shot)
            fraction = non_background_fraction(shot)

        # Render panel: the viewer's camera to a colour and a depth image.
        page.click("#use-viewer-camera")
        page.wait_for_function("document.getElementById('render-message').textContent.includes('viewer')",
                               timeout=20_000)
        page.click("#render-button")
        page.wait_for_function("document.getElementById('render-message').textContent.startsWith('Rendered')",
                               timeout=60_000)
        sizes = page.evaluate("[document.getElementById('render-color').naturalWidth,"
                              " document.getElementById('render-depth').naturalWidth]")
        assert sizes[0] > 0 and sizes[1] > 0
        assert not errors, errors
        browser.close()


def finished_synthetic(api: httpx.Client, spec) -> str:
    """A synthetic session (a spec, or a list: one agent each) with the test preset, run to its end."""
    session_id = api.post("/api/sessions", json={"source": "synthetic", "preset": "test", "spec": spec}).json()["id"]
    deadline = time.monotonic() + 150
    while (state := api.get(f"/api/sessions/{session_id}").json())["status"] != "finished":
        assert state["status"] in ("queued", "running"), f"synthetic session {spec}: {state['status']}: {state['error']}"
        assert time.monotonic() < deadline, f"synthetic session {spec} did not finish"
        time.sleep(0.5)
    return session_id


@contextmanager
def browser_page(url: str) -> Iterator:
    """Chromium on ``url`` at 1400x1000; fails the test if the page raised an error."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(url)
        yield page
        assert not errors, errors
        browser.close()


def test_render_panel_follows_the_session_and_plots_show_each_agent(server_url, tmp_path):
    """Issue 44 items 2, 3, 7, 8: the render panel starts at the selected session's last tracked
    frame with its camera (fields in step), a collaborative session's plots offer each agent, the
    header names no port, and the viewer can be made taller."""
    api = httpx.Client(base_url=server_url, timeout=30)
    session_id = finished_synthetic(api, [f"agents?agent={k}&agents=2&frames=6&width=160&height=120"
                                          for k in range(2)])
    expected = api.get(f"/api/sessions/{session_id}/camera").json()

    with browser_page(server_url + f"/?session={session_id}") as page:
        # The fields follow the session's camera: 160x120 input -> 320x240 at the panel's width.
        page.wait_for_function("document.getElementById('cam-height').value === '240' && "
                               "document.getElementById('cam-fov').value !== '60'", timeout=20_000)
        fov = float(page.input_value("#cam-fov"))
        i = expected["intrinsics"]
        assert abs(fov - 2 * np.degrees(np.arctan(i["height"] / 2 / i["fy"]))) < 0.1
        position = [float(page.input_value(f"#cam-{axis}")) for axis in "xyz"]
        assert np.allclose(position, np.array(expected["T_world_cam"])[:3, 3], atol=0.006)
        page.click("#render-button")
        page.wait_for_function("document.getElementById('render-message').textContent.startsWith('Rendered')",
                               timeout=60_000)
        shot = page.locator("#render-color").screenshot()
        (tmp_path / "render.png").write_bytes(shot)
        image = cv2.imdecode(np.frombuffer(shot, np.uint8), cv2.IMREAD_COLOR)
        assert (image.max(axis=2) > 20).mean() > 0.8, f"the view at the last pose shows the scene ({tmp_path})"

        # Per-agent plots: agent 1's series and its own ATE.
        page.wait_for_selector("#plots-agent-label:not([hidden])", timeout=20_000)
        assert page.eval_on_selector_all("#plots-agent option", "o => o.map(x => x.textContent)") == \
            ["agent 0", "agent 1"]
        page.select_option("#plots-agent", "1")
        page.wait_for_function("document.getElementById('plots-note').textContent.startsWith('agent 1: ATE')",
                               timeout=20_000)
        ate_1 = api.get(f"/api/sessions/{session_id}/series", params={"agent": 1}).json()["ate_rmse_m"]
        assert f"{ate_1 * 100:.2f} cm" in page.inner_text("#plots-note")

        # The header names no port; "taller" grows the viewer and is remembered.
        assert "port" not in page.inner_text(".viewer-card h2")
        before = page.locator("#viewer-box").bounding_box()["height"]
        page.click("#viewer-size")
        after = page.locator("#viewer-box").bounding_box()["height"]
        assert after > before + 200, (before, after)
        page.reload()
        page.wait_for_selector("#viewer-box.tall", timeout=10_000)
        page.screenshot(path=str(tmp_path / "page.png"))


def test_camera_path_panel_renders_a_video_the_browser_plays(server_url, tmp_path):
    """Issue 44 item 9: two keyframes from the render panel's camera, a one-second path, the
    server's MP4 plays in the page's video element."""
    api = httpx.Client(base_url=server_url, timeout=30)
    session_id = finished_synthetic(api, "orbit?frames=8&width=160&height=120")
    with browser_page(server_url + f"/?session={session_id}") as page:
        page.wait_for_function("document.getElementById('cam-height').value === '240'", timeout=20_000)
        page.fill("#cam-width", "160")
        page.fill("#cam-height", "120")
        page.click("#path-add-render")
        page.fill("#cam-yaw", str(float(page.input_value("#cam-yaw")) + 30))
        page.click("#pose-from-numbers")
        page.click("#path-add-render")
        assert page.inner_text("#path-count") == "2 keyframes"
        page.fill("#path-duration", "1")
        page.fill("#path-fps", "6")
        page.click("#path-button")
        page.wait_for_function("document.getElementById('path-message').textContent.startsWith('Rendered')",
                               timeout=90_000)
        page.wait_for_function("document.getElementById('path-video').readyState >= 2", timeout=20_000)
        size = page.evaluate("[document.getElementById('path-video').videoWidth,"
                             " document.getElementById('path-video').videoHeight]")
        assert size == [480, 120], size
        page.locator("#path-panel").screenshot(path=str(tmp_path / "path.png"))


def test_crop_box_bounds_the_render(server_url, tmp_path):
    """Issue 44 item 11: a crop box in the render panel hides what lies outside it."""
    api = httpx.Client(base_url=server_url, timeout=30)
    session_id = finished_synthetic(api, "orbit?frames=8&width=160&height=120")
    with browser_page(server_url + f"/?session={session_id}") as page:
        page.wait_for_function("document.getElementById('cam-height').value === '240'", timeout=20_000)

        def rendered_share() -> float:
            page.click("#render-button")
            page.wait_for_function("document.getElementById('render-message').textContent.startsWith('Rendered')",
                                   timeout=60_000)
            page.evaluate("document.getElementById('render-message').textContent = ''")
            shot = page.locator("#render-color").screenshot()
            image = cv2.imdecode(np.frombuffer(shot, np.uint8), cv2.IMREAD_COLOR)
            return float((image.max(axis=2) > 40).mean())

        whole = rendered_share()
        page.click("#crop-details summary")
        x = float(page.input_value("#cam-x"))
        for field, value in zip(["x0", "y0", "z0", "x1", "y1", "z1"], [x - 100, -100, -100, x, 100, 100]):
            page.fill(f"#crop-{field}", str(value))
        cropped = rendered_share()
        assert cropped < 0.8 * whole, (whole, cropped)
        # the second image: normals instead of depth re-renders, and hides the depth range
        page.select_option("#render-second", "normals")
        page.wait_for_function("document.getElementById('render-message').textContent.startsWith('Rendered')",
                               timeout=60_000)
        assert not page.is_visible("#depth-range")
        page.fill("#crop-x1", str(x - 200))
        page.click("#render-button")
        page.wait_for_function("document.getElementById('render-message').textContent.includes('below its max')",
                               timeout=10_000)


def test_viewer_shows_the_neural_map_instead_of_the_mesh(server_url, tmp_path):
    """Issue 44 item 10: the viewer's Surface choice renders the map from the browser's camera
    (here colour | depth, split down the middle) as the scene's background."""
    api = httpx.Client(base_url=server_url, timeout=30)
    session_id = finished_synthetic(api, "orbit?frames=8&width=160&height=120")
    with browser_page(server_url + f"/?session={session_id}") as page:
        deadline = time.monotonic() + 90
        while api.get("/api/viewer").json()["clients"] < 1:
            assert time.monotonic() < deadline, "the embedded viewer did not connect"
            time.sleep(0.5)
        frame = page.frame_locator("#viewer-frame")
        frame.locator("input[value='mesh']").first.click()
        frame.locator("text=colour | depth").last.click()
        viewer = page.locator("#viewer-frame")
        shot = None
        while True:  # the split view: grey-green colour on the left, the turbo depth map on the right
            time.sleep(1.0)
            shot = cv2.imdecode(np.frombuffer(viewer.screenshot(), np.uint8), cv2.IMREAD_COLOR)
            h, w = shot.shape[:2]
            right = shot[h // 4: 3 * h // 4, int(0.45 * w): int(0.65 * w)].astype(int)
            saturated = (right.max(axis=2) - right.min(axis=2) > 120).mean()
            if saturated > 0.2:
                break
            assert time.monotonic() < deadline, f"no neural depth in the viewer (see {tmp_path / 'neural.png'})"
            cv2.imwrite(str(tmp_path / "neural.png"), shot)
        cv2.imwrite(str(tmp_path / "neural.png"), shot)
