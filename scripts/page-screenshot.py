"""Retake docs/page.png, the README's picture of the page: a server on 127.0.0.1 with one
finished synthetic session (test preset), the render panel's view at its last pose, an AR cube
and a camera-path video, in Chromium at 1400 px wide.

    .venv/bin/python scripts/page-screenshot.py [--out docs/page.png] [--frames 150]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.live_server import start_uvicorn  # noqa: E402
from tests.test_browser import CHROMIUM, CHROMIUM_ARGS, finished_synthetic  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "page.png")
    parser.add_argument("--frames", type=int, default=150)
    args = parser.parse_args()

    import httpx
    from playwright.sync_api import sync_playwright

    from server.main import create_app
    from server.settings import Settings

    with tempfile.TemporaryDirectory() as data:
        live = start_uvicorn(create_app(Settings(data_dir=Path(data), viewer_port=0, max_sessions=1)))
        try:
            api = httpx.Client(base_url=live.url, timeout=60)
            session_id = finished_synthetic(api, f"orbit?frames={args.frames}&width=320&height=240")
            with sync_playwright() as playwright:
                browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
                page = browser.new_page(viewport={"width": 1400, "height": 1000})
                page.goto(f"{live.url}/?session={session_id}")
                page.wait_for_function("document.getElementById('cam-height').value === '240'", timeout=30_000)
                page.click("#render-button")
                page.wait_for_function("document.getElementById('render-message').textContent.startsWith('Rendered')",
                                       timeout=120_000)
                page.click("#ar-auto")
                page.wait_for_function("document.getElementById('ar-message').textContent.startsWith('Done')",
                                       timeout=120_000)
                page.click("#path-add-render")
                page.fill("#cam-yaw", f"{float(page.input_value('#cam-yaw')) + 40:.1f}")
                page.click("#pose-from-numbers")
                page.click("#path-add-render")
                page.fill("#path-duration", "2")
                page.fill("#path-fps", "8")
                page.click("#path-button")
                page.wait_for_function("document.getElementById('path-message').textContent.startsWith('Rendered')",
                                       timeout=300_000)
                time.sleep(8)  # the viewer draws the mesh (software WebGL)
                page.screenshot(path=str(args.out), full_page=True)
                browser.close()
        finally:
            live.stop()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
