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


def viewer_shot(page, path: Path) -> np.ndarray:
    """The viewer's scene left of its docked panel, as BGR pixels (also written to ``path``)."""
    shot = cv2.imdecode(np.frombuffer(page.screenshot(), np.uint8), cv2.IMREAD_COLOR)
    cv2.imwrite(str(path), shot)
    h, w = shot.shape[:2]
    return shot[int(0.2 * h): int(0.9 * h), int(0.1 * w): int(0.6 * w)].astype(int)


def wait_for_shots(pages, path: Path, name: str, done, timeout_s: float = 40.0) -> list[np.ndarray]:
    """Shots of every page (``name_<k>.png`` under ``path``) until ``done(shots)`` holds (or the
    time is up: the caller's assertion then says what is wrong)."""
    deadline = time.monotonic() + timeout_s
    while True:
        time.sleep(1.0)
        shots = [viewer_shot(page, path / f"{name}_{k}.png") for k, page in enumerate(pages)]
        if done(shots) or time.monotonic() > deadline:
            return shots


def same_picture(a: np.ndarray, b: np.ndarray) -> float:
    """Share of pixels drawn (not background) in both or neither of two shots: the lighting of
    software WebGL settles for a while after the scene comes, the shapes do not."""
    return float(((a.min(axis=2) < 235) == (b.min(axis=2) < 235)).mean())


@contextmanager
def two_viewers(server_url: str, tmp_path: Path) -> Iterator[tuple]:
    """A finished synthetic session shown by two browsers (contexts) on the viewer alone:
    (api, session id, the chromium, the two pages, their first shots once the mesh is drawn)."""
    from playwright.sync_api import sync_playwright

    api = httpx.Client(base_url=server_url, timeout=30)
    session_id = finished_synthetic(api, "orbit?frames=8&width=160&height=120")
    api.post(f"/api/viewer/select/{session_id}")
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        pages = [browser.new_context(viewport={"width": 1000, "height": 600}).new_page() for _ in range(2)]
        for page in pages:
            page.goto(server_url + "/viewer")
        deadline = time.monotonic() + 90
        while api.get("/api/viewer").json()["clients"] < 2:
            assert time.monotonic() < deadline, "the two viewers did not connect"
            time.sleep(0.5)
        wait_for_shots(pages, tmp_path, "before", lambda shots: min((s.min(axis=2) < 235).mean() for s in shots) > 0.05)
        time.sleep(3.0)  # the lighting settles
        before = wait_for_shots(pages, tmp_path, "before", lambda shots: True)
        assert (before[0].min(axis=2) < 235).mean() > 0.05, f"no mesh to begin with ({tmp_path})"
        yield api, session_id, browser, pages, before
        browser.close()


def test_each_browser_has_its_own_viewer_controls(server_url, tmp_path):
    """Issue 44 item 4: two browsers on the viewer; one colours the meshes by map and then hides
    them, the other's controls and picture do not change."""
    with two_viewers(server_url, tmp_path) as (api, session_id, browser, pages, before):
        mine, other = pages
        mine.get_by_text("Colour meshes by map").click()
        orange = lambda image: ((image[..., 2] > 150) & (image[..., 2] - image[..., 0] > 80)).mean()  # noqa: E731
        tinted = wait_for_shots(pages, tmp_path, "tinted", lambda shots: orange(shots[0]) > 0.03)
        assert orange(tinted[0]) > 0.03 > orange(tinted[1]), (orange(tinted[0]), orange(tinted[1]), str(tmp_path))
        assert same_picture(tinted[1], before[1]) > 0.98, f"the other browser's picture changed ({tmp_path})"

        mine.get_by_text("Meshes", exact=True).click()
        hidden = wait_for_shots(pages, tmp_path, "hidden", lambda shots: orange(shots[0]) < 0.01)
        assert (hidden[0].min(axis=2) < 235).mean() < 0.5 * (before[0].min(axis=2) < 235).mean(), str(tmp_path)
        assert same_picture(hidden[1], before[1]) > 0.98, f"the other browser's picture changed ({tmp_path})"
        assert other.get_by_label("Colour meshes by map").is_checked() is False
        assert other.get_by_label("Meshes", exact=True).is_checked()


def test_a_crop_box_in_one_viewer_crops_its_mesh_and_the_page_takes_it(server_url, tmp_path):
    """Issue 44 item 11: one browser's crop box (viewer panel) hides the mesh outside it in that
    browser only, links its cropped mesh, and the page's crop fields take it from the viewer."""
    with two_viewers(server_url, tmp_path) as (api, session_id, browser, viewers, before):
        mine = viewers[0]
        mine.get_by_text("Crop box").click()
        mine.get_by_text("Fit to the session").click()
        fields = mine.locator("input[inputmode='decimal']")
        mine.wait_for_function("document.querySelector(\"input[inputmode='decimal']\").value !== '-1'")
        lo, hi = float(fields.nth(0).input_value()), float(fields.nth(3).input_value())
        middle = round((lo + hi) / 2, 2)
        fields.nth(0).fill(str(middle))
        fields.nth(0).press("Enter")
        mine.get_by_text("Crop", exact=True).click()
        # The mesh's pixels: the box's own blue lines (CROP_COLOR) are drawn only after the crop,
        # and over a thin mesh they make up a fifth of what the crop removed.
        drawn = lambda image: ((image.min(axis=2) < 235) & (image[..., 0] - image[..., 2] <= 80)).mean()  # noqa: E731
        after = wait_for_shots(viewers, tmp_path, "cropped", lambda shots: drawn(shots[0]) < 0.8 * drawn(before[0]))
        assert drawn(after[0]) < 0.8 * drawn(before[0]), (drawn(before[0]), drawn(after[0]), str(tmp_path))
        assert same_picture(after[1], before[1]) > 0.98, f"the other browser's picture changed ({tmp_path})"

        box = api.get("/api/viewer/crop").json()
        assert box["min"][0] == pytest.approx(middle) and box["max"][0] == pytest.approx(hi)
        link = mine.locator("a", has_text="PLY").get_attribute("href")
        assert link.startswith(f"/api/sessions/{session_id}/mesh?format=ply&crop="), link
        import trimesh

        cropped = trimesh.load(io.BytesIO(api.get(link).content), file_type="ply", process=False)
        assert len(cropped.faces) and cropped.vertices[:, 0].min() >= middle - 1e-4

        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        page.goto(server_url + f"/?session={session_id}")
        page.click("#crop-details summary")
        page.click("#crop-from-viewer")
        page.wait_for_function("document.getElementById('crop-x0').value !== ''", timeout=20_000)
        assert float(page.input_value("#crop-x0")) == pytest.approx(middle, abs=1e-3)
        page.locator("#crop-details").screenshot(path=str(tmp_path / "page_crop.png"))
