"""Renders, picks, AR composites, mesh exports and path videos run in helper processes with a
budget (server.render_pools, server.helper_pool): the same answers as the in-process
functions, 503/429 with Retry-After past the limits, 422 for a video over its pixel budget,
504 past the time limit with the helper replaced, and no map loaded in the API process."""

from __future__ import annotations

import io
import threading
import time

import numpy as np
import pytest
import trimesh

from tests.test_server_api import (
    client,  # noqa: F401 - fixtures
    data_dir,  # noqa: F401
    decode_png,
    first_pose_camera,
    needs_runtime,
    synthetic_session,  # noqa: F401
)


def in_process_view(client, session_id: str, camera: dict):  # noqa: F811
    """(map set, Camera, RenderedView) as the API process rendered them before the helpers."""
    from server.rendering import Camera, intrinsics_matrix, render
    from slam import load_checkpoint

    mapset = load_checkpoint(client.app.state.manager.session_dir(session_id) / "map.pt", device="cpu")
    i = camera["intrinsics"]
    view_camera = Camera(np.array(camera["T_world_cam"]), intrinsics_matrix(i["fx"], i["fy"], i["cx"], i["cy"]),
                         i["width"], i["height"])
    return mapset, view_camera, render(mapset, view_camera)


def test_the_pool_refuses_at_once_past_its_queue_and_gives_up_after_its_wait():
    from server.helper_pool import HelperKind, HelperPool, PoolBusy

    pool = HelperPool(HelperKind("test", "testing", "test", 256 * 2**20, 30.0), size=1, max_waiting=1, wait_s=0.3,
                      retry_after_s=7)
    with pool.lease():
        started = time.monotonic()
        with pytest.raises(PoolBusy, match="came free within 0.3 s") as waited:
            with pool.lease():
                pass
        assert 0.25 < time.monotonic() - started < 5 and waited.value.retry_after_s == 7
    pool.close()


@needs_runtime
def test_render_pick_ar_and_mesh_answer_as_the_in_process_functions_without_a_map_in_the_api(
        client, synthetic_session, monkeypatch):  # noqa: F811
    import slam
    from ar import load_objects_json
    from server.ar_compose import Background, composite_png
    from server.rendering import MeshFiles, pick_surface, png_from_depth, png_from_rgb

    loads = []
    monkeypatch.setattr(slam, "load_checkpoint", lambda *a, **k: loads.append(a))  # the API's MapCache loads here
    url = f"/api/sessions/{synthetic_session}"
    camera = first_pose_camera(client, synthetic_session)
    color = client.post(f"{url}/render", json=camera)
    depth = client.post(f"{url}/render", json=camera, params={"output": "depth"})
    picked = client.post(f"{url}/pick", json={**camera, "u": 40, "v": 30})
    objects = [{"shape": "cube", "scale": 0.2, "color": [1, 0, 0]}]
    composite = client.post(f"{url}/ar", json={"background": "render", **camera, "objects": objects})
    glb = client.get(f"{url}/mesh", params={"format": "glb"})
    cropped = client.get(f"{url}/mesh", params={"format": "ply", "crop": "-10,-10,-10,10,10,10"})
    for response in (color, depth, picked, composite, glb, cropped):
        assert response.status_code == 200, response.text
    assert loads == [] and client.app.state.map_cache._entries == {}, "the API process loaded a map"
    monkeypatch.undo()

    mapset, view_camera, view = in_process_view(client, synthetic_session, camera)
    np.testing.assert_array_equal(decode_png(color.content), decode_png(png_from_rgb(view.rgb)))
    np.testing.assert_array_equal(decode_png(depth.content), decode_png(png_from_depth(view.depth)))
    expected = pick_surface(mapset, view_camera, 40, 30)
    assert picked.json()["hit"] == (expected is not None)
    if expected is not None:
        np.testing.assert_allclose(picked.json()["point"], expected.point, atol=1e-5)
    background = Background(np.asarray(view.rgb), np.asarray(view.depth), view_camera)
    png, report = composite_png(background, load_objects_json(objects), [False])
    np.testing.assert_array_equal(decode_png(composite.content), decode_png(png))
    assert composite.headers["X-AR-Objects"].replace(" ", "") == str(report).replace("'", '"').replace(" ", "")
    ply = client.app.state.manager.session_dir(synthetic_session) / "mesh.ply"
    served = trimesh.load(io.BytesIO(glb.content), file_type="glb", force="mesh")
    made = trimesh.load(io.BytesIO(MeshFiles().convert(ply, "glb")), file_type="glb", force="mesh")
    np.testing.assert_array_equal(served.vertices, made.vertices)
    np.testing.assert_array_equal(served.faces, made.faces)
    whole = trimesh.load(ply, file_type="ply", process=False)
    assert len(trimesh.load(io.BytesIO(cropped.content), file_type="ply", process=False).faces) == len(whole.faces)


@needs_runtime
def test_renders_past_the_helpers_and_their_queue_get_503_with_retry_after(client, synthetic_session,
                                                                         monkeypatch):  # noqa: F811
    pool = client.app.state.render_pools.render
    monkeypatch.setattr(pool, "wait_s", 0.5)
    url = f"/api/sessions/{synthetic_session}"
    camera = first_pose_camera(client, synthetic_session)
    answers = []

    def ask(call: str, body: dict) -> None:
        answers.append(client.post(f"{url}/{call}", json=body))

    leases = [pool.lease() for _ in range(pool.size)]
    for lease in leases:  # every helper busy, as with renders that take long
        lease.__enter__()
    try:
        threads = [threading.Thread(target=ask, args=(call, body)) for call, body in
                   [("render", camera)] * 4 + [("pick", {**camera, "u": 1, "v": 1}),
                                               ("ar", {"background": "render", **camera, "objects": []})]]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=30)
    finally:
        for lease in leases:
            lease.__exit__(None, None, None)
    assert [a.status_code for a in answers] == [503] * 6, [a.text for a in answers]
    for answer in answers:
        assert int(answer.headers["Retry-After"]) > 0 and "busy" in answer.json()["detail"]
    assert client.post(f"{url}/render", json=camera).status_code == 200, "a helper came free: renders again"


@needs_runtime
def test_a_render_past_its_time_limit_gets_504_and_the_next_one_a_new_helper(client, synthetic_session,
                                                                            monkeypatch):  # noqa: F811
    pools = client.app.state.render_pools
    url = f"/api/sessions/{synthetic_session}/render"
    camera = first_pose_camera(client, synthetic_session)
    assert client.post(url, json=camera).status_code == 200
    before = set(pools.render.pids())
    monkeypatch.setattr(pools.render, "timeout_s", 0.2)
    big = first_pose_camera(client, synthetic_session, width=1024, height=768, f=700.0)
    response = client.post(url, json=big)
    assert response.status_code == 504, response.text
    assert "rendering took longer than 0.2 s" in response.json()["detail"]
    monkeypatch.undo()
    assert client.post(url, json=camera).status_code == 200
    assert set(pools.render.pids()) != before, "the helper that ran out of time was replaced"


def test_a_video_over_the_pixel_budget_gets_422_with_the_numbers(client):  # noqa: F811
    created = client.post("/api/sessions", json={"source": "stream", "preset": "test"}).json()
    body = {"keyframes": [np.eye(4).tolist()] * 2, "duration_s": 60, "fps": 60,
            "intrinsics": {"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}}
    response = client.post(f"/api/sessions/{created['id']}/render/path", json=body)
    assert response.status_code == 422, response.text
    assert "3600 frames of 640x480 = 1,105.9 million pixels; at most 200 million" in response.json()["detail"]
    client.delete(f"/api/sessions/{created['id']}")


@needs_runtime
def test_too_many_video_jobs_get_429_and_a_job_reports_its_frames(client, synthetic_session,
                                                                   monkeypatch):  # noqa: F811
    MAX_VIDEO_JOBS = 2  # noqa: N806 - the budget's, made small to keep the test short
    monkeypatch.setattr(client.app.state.path_jobs, "max_jobs", MAX_VIDEO_JOBS)
    url = f"/api/sessions/{synthetic_session}/render/path"
    camera = first_pose_camera(client, synthetic_session, width=32, height=24, f=24.0)
    body = {"keyframes": [camera["T_world_cam"]] * 2, "intrinsics": camera["intrinsics"], "duration_s": 1.0,
            "fps": 3, "outputs": ["color"]}
    answers = [client.post(url, json=body) for _ in range(MAX_VIDEO_JOBS + 2)]
    assert [a.status_code for a in answers] == [202] * MAX_VIDEO_JOBS + [429] * 2, [a.text for a in answers]
    assert int(answers[-1].headers["Retry-After"]) > 0 and "queued or rendering" in answers[-1].json()["detail"]
    deadline = time.monotonic() + 120
    jobs = [a.json() for a in answers[:MAX_VIDEO_JOBS]]
    while any(j["state"] not in ("finished", "failed") for j in jobs):
        assert time.monotonic() < deadline, jobs
        time.sleep(0.3)
        jobs = [client.get(f"{url}/{j['id']}").json() for j in jobs]
    assert all(j["state"] == "finished" and j["frames_done"] == j["frames_total"] == 3 for j in jobs), jobs
    assert client.post(url, json=body).status_code == 202, "the finished jobs made room"


def test_the_decode_helper_is_served_as_before_by_shared_helper():
    from server.decoding import DecodeFailed, shared_helper
    from server.helper_pool import HelperFailed

    assert shared_helper().call(np.add, 2, 3) == 5 and DecodeFailed is HelperFailed


def test_helper_threads_sleep_when_idle_instead_of_spinning():
    """Helpers share two cores with each other and the sessions: OpenMP's idle threads must not
    spin there (a spinning thread without a core of its own stalls every operation)."""
    import os

    from server.decoding import shared_helper

    assert shared_helper().call(os.getenv, "OMP_WAIT_POLICY") == "PASSIVE"
