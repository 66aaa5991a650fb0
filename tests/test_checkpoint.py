"""Map checkpoints: round trip, weights-only loading, corrupt files and versions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from slam.checkpoint import (CHECKPOINT_VERSION, CheckpointError, load_checkpoint, load_checkpoint_extra,
                             save_checkpoint)
from slam.maps import Keyframe, MapSet
from slam.mesh import extract_mesh
from slam.views import render_view
from tests.test_mesh_views import CONFIG, exact_submap, patch, pinhole, plane_z, translation

K = pinhole(32, 24, 16.0)


@pytest.fixture(scope="module")
def mapset() -> MapSet:
    """Two submaps, one moved and rotated, one with a keyframe."""
    yaw = 0.3
    T = translation(x=0.4, z=0.8)
    T[:3, :3] = torch.tensor([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    first = exact_submap(patch(-2, 2), plane_z(0.13), map_id=0, T_world_map=translation(z=1.0))
    second = exact_submap(patch(-2, 2), plane_z(0.07), map_id=1, T_world_map=T)
    second.keyframes.append(Keyframe(frame_index=7, timestamp=0.25, frame=None,
                                     K=torch.from_numpy(K).float(), T_map_cam=translation(y=0.1)))
    # The second map knows which voxels were optimised and held surface; the first does not.
    second.corner_updates = torch.arange(second.voxels.num_corners, dtype=torch.int32) % 5 + 1
    second.observe_surface(second.voxels.voxel_codes[:10])
    return MapSet(CONFIG, [first, second])


def test_round_trip_renders_and_meshes_identically(mapset, tmp_path):
    path = save_checkpoint(mapset, tmp_path / "map.pt")
    assert path == tmp_path / "map.pt"
    assert [p.name for p in tmp_path.iterdir()] == ["map.pt"]  # no temporary file left
    loaded = load_checkpoint(path)
    assert loaded.config == mapset.config
    assert [m.map_id for m in loaded.maps] == [0, 1]
    for before, after in zip(mapset.maps, loaded.maps):
        assert torch.equal(before.voxels.embeddings, after.voxels.embeddings)
        assert torch.equal(before.T_world_map, after.T_world_map)
        for name in ("corner_updates", "surface_codes"):
            a, b = getattr(before, name), getattr(after, name)
            assert (a is None and b is None) or torch.equal(a, b), name
    assert loaded.maps[1].surface_codes.numel() == 10
    keyframe = loaded.maps[1].keyframes[0]
    assert keyframe.frame_index == 7 and torch.equal(keyframe.T_map_cam, translation(y=0.1))

    view_before = render_view(mapset, np.eye(4), K, 32, 24)
    view_after = render_view(loaded, np.eye(4), K, 32, 24)
    assert view_before.valid.any()
    np.testing.assert_array_equal(view_before.depth, view_after.depth)
    np.testing.assert_array_equal(view_before.rgb, view_after.rgb)
    mesh_before, mesh_after = extract_mesh(mapset, 2), extract_mesh(loaded, 2)
    assert len(mesh_before.faces) > 0
    np.testing.assert_array_equal(mesh_before.vertices, mesh_after.vertices)
    np.testing.assert_array_equal(mesh_before.faces, mesh_after.faces)
    np.testing.assert_array_equal(mesh_before.visual.vertex_colors, mesh_after.visual.vertex_colors)


def test_file_is_plain_data_loadable_weights_only(mapset, tmp_path):
    path = save_checkpoint(mapset, tmp_path / "map.pt")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    assert payload["version"] == CHECKPOINT_VERSION
    assert payload["config"]["preset"] == "test"
    assert len(payload["maps"]) == 2


def test_extra_metadata_round_trip(mapset, tmp_path):
    trajectory = np.random.default_rng(0).normal(size=(5, 8))
    extra = {"frames": 12, "name": "office0", "fps": np.float32(2.5), "trajectory": trajectory,
             "nested": {"ids": (1, 2), "pose": torch.eye(4), "none": None}}
    path = save_checkpoint(mapset, tmp_path / "map.pt", extra=extra)
    loaded = load_checkpoint_extra(path)
    assert loaded["frames"] == 12 and loaded["name"] == "office0" and loaded["fps"] == 2.5
    assert isinstance(loaded["trajectory"], np.ndarray)
    np.testing.assert_array_equal(loaded["trajectory"], trajectory)
    assert loaded["nested"]["ids"] == [1, 2] and loaded["nested"]["none"] is None
    assert torch.equal(loaded["nested"]["pose"], torch.eye(4))
    assert load_checkpoint_extra(save_checkpoint(mapset, tmp_path / "bare.pt")) == {}


def test_extra_that_cannot_be_stored_is_rejected(mapset, tmp_path):
    with pytest.raises(TypeError, match="extra.bad"):
        save_checkpoint(mapset, tmp_path / "map.pt", extra={"bad": object()})
    assert not (tmp_path / "map.pt").exists()


def test_overwrite_replaces_the_old_file(mapset, tmp_path):
    path = tmp_path / "map.pt"
    save_checkpoint(MapSet(CONFIG, mapset.maps[:1]), path)
    save_checkpoint(mapset, path)
    assert len(load_checkpoint(path).maps) == 2


@pytest.mark.parametrize("damage", ["garbage", "truncated", "empty"])
def test_corrupt_file_raises_checkpoint_error(mapset, tmp_path, damage):
    path = save_checkpoint(mapset, tmp_path / "map.pt")
    data = path.read_bytes()
    path.write_bytes({"garbage": b"not a checkpoint" * 50, "truncated": data[: len(data) // 2],
                      "empty": b""}[damage])
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(path)
    with pytest.raises(CheckpointError):
        load_checkpoint_extra(path)


@pytest.mark.parametrize("version, message", [(CHECKPOINT_VERSION + 1, "newer"), (0, "unknown format version"),
                                              ("1", "no format version")])
def test_version_mismatch_raises_checkpoint_error(mapset, tmp_path, version, message):
    path = save_checkpoint(mapset, tmp_path / "map.pt")
    payload = torch.load(path, weights_only=True)
    payload["version"] = version
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(path)


def test_other_files_raise_checkpoint_error(mapset, tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.pt")
    torch.save(torch.zeros(3), tmp_path / "tensor.pt")
    with pytest.raises(CheckpointError, match="not a voxfusion map checkpoint"):
        load_checkpoint(tmp_path / "tensor.pt")
    path = save_checkpoint(mapset, tmp_path / "map.pt")
    payload = torch.load(path, weights_only=True)
    del payload["maps"][0]["voxels"]
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match="submap"):
        load_checkpoint(path)


def test_loads_on_the_cpu_whatever_device_wrote_it(mapset, tmp_path):
    device = "cuda" if torch.cuda.is_available() else "meta"
    if device == "meta":
        pytest.skip("no CUDA device to write from")
    on_device = load_checkpoint(save_checkpoint(mapset, tmp_path / "a.pt"), device=device)
    path = save_checkpoint(on_device, tmp_path / "b.pt")
    loaded = load_checkpoint(path, device="cpu")
    assert loaded.maps[0].voxels.embeddings.device.type == "cpu"
    assert torch.equal(loaded.maps[0].voxels.embeddings, mapset.maps[0].voxels.embeddings)
