"""The executor seam without a cluster: settings, the local executor's ``worker``, and the Ray
executor's file shipping helpers (pure functions; Ray itself is not imported)."""

from __future__ import annotations

import pytest

from server.execution import WorkerInfo, describe_exit
from server.executors import LocalExecutor, make_executor
from server.ray_executor import pack_input, probe, relocate, unpack_input, write_files
from server.sessions import SessionStatus
from server.settings import Settings, SettingsError, settings_from_env
from server.worker import SourceSpec, WorkerJob


def test_executor_settings(tmp_path):
    env = {"VOXFUSION_DATA_DIR": str(tmp_path)}
    local = settings_from_env(env)
    assert local.executor == "local" and local.max_sessions >= 1
    assert isinstance(make_executor(local), LocalExecutor)
    ray = settings_from_env({**env, "VOXFUSION_EXECUTOR": "Ray", "VOXFUSION_RAY_ADDRESS": "10.0.0.1:6379",
                             "VOXFUSION_RAY_SESSION_CPUS": "4", "VOXFUSION_RAY_LOST_S": "5"})
    assert (ray.executor, ray.ray_address, ray.ray_session_cpus, ray.ray_lost_s) == ("ray", "10.0.0.1:6379", 4.0, 5.0)
    assert ray.max_sessions == 64, "Ray queues what does not fit: the API hands it many"
    with pytest.raises(SettingsError, match="VOXFUSION_EXECUTOR"):
        settings_from_env({**env, "VOXFUSION_EXECUTOR": "kubernetes"})
    with pytest.raises(SettingsError, match="VOXFUSION_RAY_LOST_S"):
        settings_from_env({**env, "VOXFUSION_RAY_LOST_S": "0"})


def test_worker_is_kept_in_session_json_and_old_files_still_load():
    status = SessionStatus(id="aaaaaaaaaaaa", status="running", created="2026-01-01T00:00:00+00:00",
                           source="synthetic:orbit", preset="test",
                           worker=WorkerInfo(executor="ray", node="abc", address="10.0.0.2"))
    assert SessionStatus.from_json(status.to_json()) == status
    old = status.to_json()
    del old["worker"]
    assert SessionStatus.from_json(old).worker is None


def test_input_travels_and_paths_follow(tmp_path):
    api = tmp_path / "api" / "sessions" / "aaaaaaaaaaaa"
    (api / "input" / "desk" / "rgb").mkdir(parents=True)
    (api / "input" / "desk" / "rgb" / "1.png").write_bytes(b"png")
    job = WorkerJob(session_id="aaaaaaaaaaaa", preset="test", out_dir=str(api),
                    sources=(SourceSpec(kind="dataset", path=str(api / "input" / "desk")),))
    node = tmp_path / "node" / "aaaaaaaaaaaa-1234"
    node.mkdir(parents=True)
    unpack_input(pack_input(api / "input"), node)
    moved = relocate(job, str(api), str(node))
    assert moved.out_dir == str(node) and moved.source.path == str(node / "input" / "desk")
    assert (node / "input" / "desk" / "rgb" / "1.png").read_bytes() == b"png"
    synthetic = WorkerJob(session_id="b" * 12, preset="test", out_dir=str(api),
                          sources=(SourceSpec(kind="synthetic", path="orbit"),))
    assert relocate(synthetic, str(api), str(node)).source.path == "orbit", "a generator spec is not a path"


def test_shipped_files_land_atomically_and_odd_names_are_refused(tmp_path, capsys):
    write_files(tmp_path, {"map.pt": b"new", "../escape.txt": b"x", ".hidden": b"y"})
    assert (tmp_path / "map.pt").read_bytes() == b"new"
    assert not (tmp_path.parent / "escape.txt").exists() and not (tmp_path / ".hidden").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["map.pt"], "no temporary file is left"
    assert "odd name" in capsys.readouterr().out


def test_probe_and_exit_descriptions():
    import socket

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        assert probe(f"127.0.0.1:{server.getsockname()[1]}") is None
        port = server.getsockname()[1]
    assert probe(f"127.0.0.1:{port}") is not None, "nothing listens there now"
    assert probe("no-port") is not None
    assert "SIGKILL" in describe_exit(-9) and "code 3" in describe_exit(3)


def test_local_sessions_say_where_they_run(tmp_path):
    import socket
    import time

    from server.sessions import SessionManager

    manager = SessionManager(Settings(data_dir=tmp_path))
    manager.settings.sessions_dir.mkdir(parents=True)
    manager.start()
    try:
        manager.create("cccccccccccc", SourceSpec(kind="synthetic", path="orbit?frames=2&width=40&height=30"),
                       "test")
        deadline = time.monotonic() + 30
        while manager.get("cccccccccccc").worker is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert manager.get("cccccccccccc").worker == WorkerInfo(executor="local", node=socket.gethostname())
    finally:
        manager.stop(grace_s=1.0)
