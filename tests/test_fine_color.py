"""The fine colour level (slam.fine_color): hash features against their reference, training by
mapping only (the coarse map unchanged), views, meshes and checkpoints with and without it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from slam.checkpoint import load_checkpoint, save_checkpoint
from slam.config import ConfigError, FineColorConfig, apply_overrides, preset
from slam.data import open_sequence
from slam.fine_color import (FineColor, corner_rows_and_weights, fine_loss, hash_features,
                             hash_features_reference, level_cells, level_rows, with_fine)
from slam.frames import prepare_frame
from slam.mapping import Mapper, TrackedFrame
from slam.maps import MapSet
from slam.mesh import extract_submap_mesh
from slam.views import coarse_surface, render_view
from tests.test_mesh_views import CONFIG, exact_submap, patch, pinhole, plane_z, single_thread  # noqa: F401 (autouse)

FINE = FineColorConfig(levels=3, features=2, table_log2=8, coarsest=0.08, finest=0.02)
BY_SURFACE = replace(FINE, level_tables="surface")
CPU = torch.device("cpu")


def test_levels_run_from_coarsest_to_finest():
    assert level_cells(FINE).tolist() == pytest.approx([0.08, 0.04, 0.02])


def test_surface_tables_shrink_with_the_area_a_coarser_cell_covers():
    assert level_rows(FINE) == [256, 256, 256]
    assert level_rows(BY_SURFACE) == [16, 64, 256]  # cells 0.08, 0.04, 0.02: 16x, 4x, 1x fewer rows
    paper_like = FineColorConfig(levels=4, table_log2=16, coarsest=0.16, finest=0.02, level_tables="surface")
    assert level_rows(paper_like) == [1 << 10, 1 << 12, 1 << 14, 1 << 16]
    assert level_rows(replace(paper_like, table_log2=5)) == [16, 16, 16, 32]  # never below 16 rows
    assert FineColor(BY_SURFACE).tables.shape == (16 + 64 + 256, 2)
    with pytest.raises(ConfigError):
        replace(FINE, level_tables="bigger")


@pytest.mark.parametrize("config", [FINE, BY_SURFACE], ids=["equal", "surface"])
def test_hash_features_match_the_reference_and_weights_sum_to_one(config):
    fine = FineColor(config, seed=3)
    with torch.no_grad():
        fine.tables.normal_()
    points = torch.randn(50, 3) * 2.0  # negative coordinates too
    rows, weights = corner_rows_and_weights(points, fine.cells, fine.rows)
    assert rows.shape == weights.shape == (50, 3, 8)
    starts = torch.cumsum(fine.rows, 0) - fine.rows
    for level in range(3):  # each level reads its own table only
        assert bool((rows[:, level] >= starts[level]).all() and (rows[:, level] < starts[level] + fine.rows[level]).all())
    torch.testing.assert_close(weights.sum(-1), torch.ones(50, 3))
    features = hash_features(points, fine.tables, fine.cells, fine.rows)
    assert features.shape == (50, 6)
    torch.testing.assert_close(features, hash_features_reference(points, fine.tables, fine.cells, fine.rows))
    assert fine(points).shape == (50, 3)


def test_fine_loss_trains_only_the_fine_level():
    fine = FineColor(FINE)
    o, d = torch.zeros(8, 3, requires_grad=True), torch.rand(8, 3, requires_grad=True)
    color, depth = torch.rand(8, 3, requires_grad=True), torch.rand(8, requires_grad=True)
    fine_loss(fine, o, d, color, depth, torch.ones(8, dtype=torch.bool), torch.rand(8, 3)).backward()
    assert all(t.grad is None for t in (o, d, color, depth))
    assert fine.tables.grad is not None and fine.tables.grad.abs().sum() > 0


def test_config_checks_the_fine_level():
    with pytest.raises(ConfigError):
        FineColorConfig(levels=-1)
    with pytest.raises(ConfigError):
        FineColorConfig(levels=2, finest=0.1, coarsest=0.05)
    with pytest.raises(ConfigError, match="fit_render_block"):
        FineColorConfig(fit_render_block=0)
    assert preset("test").fine_color.levels == 0


# ------------------------------------------------------------ mapping
def _frames(count: int = 2):
    return [prepare_frame(f, None, CPU, preset("test").voxel.max_depth)
            for f in open_sequence("synthetic:orbit?frames=100&width=80&height=60", max_frames=count)]


def _mapped(levels: int, static: str = "off", surface: str = "observed", fine: FineColorConfig = FINE) -> Mapper:
    base = preset("test")
    config = replace(base, fine_color=replace(fine, levels=levels, final_fit_surface=surface),
                     render=replace(base.render, static_shapes=static))
    mapper = Mapper(config, CPU, seed=0)
    for frame in _frames():
        mapper.process(TrackedFrame(frame, torch.from_numpy(frame.T_world_cam_gt).float()))
    mapper.global_bundle_adjustment(mapper.current, 3, 128)
    return mapper


@pytest.mark.parametrize("static, surface", [("off", "observed"), ("on", "observed"), ("off", "rendered")])
def test_mapping_trains_the_fine_level_and_leaves_the_coarse_map_as_without_it(static, surface):
    # flat samples (slam.render) and padded (slam.padded); both final fits
    with_level, without = _mapped(3, static, surface), _mapped(0, static)
    a, b = with_level.current, without.current
    assert b.fine is None and a.fine is not None
    assert torch.equal(a.voxels.embeddings, b.voxels.embeddings)
    for (name, p), q in zip(a.decoder.state_dict().items(), b.decoder.state_dict().values()):
        assert torch.equal(p, q), name
    for ka, kb in zip(a.keyframes, b.keyframes):
        assert torch.equal(ka.T_map_cam, kb.T_map_cam)
    assert a.fine.tables.abs().max() > 10 * 1e-4  # trained away from its initial range
    assert "fine_fit" in with_level.timer.totals


# ------------------------------------------------------------ views, meshes, checkpoints
def _shifted(submap, shift: float):
    """``submap`` with a fine level whose residual is ``shift`` everywhere."""
    submap.fine = FineColor(FINE)
    with torch.no_grad():
        submap.fine.tables.zero_()
        submap.fine.head.bias.fill_(shift)
    return submap


def test_with_fine_adds_the_residual_on_surface_rays_only():
    color = torch.full((4, 3), 0.5)
    surface = torch.tensor([True, False, True, False])
    fine = _shifted(exact_submap(patch(0, 1), plane_z(0.1)), 0.7).fine
    out = with_fine(fine, torch.zeros(4, 3), torch.ones(4, 3), color, torch.ones(4), surface)
    assert out[surface].eq(1.0).all() and out[~surface].eq(0.5).all()  # clamped to 1
    assert with_fine(None, torch.zeros(4, 3), torch.ones(4, 3), color, torch.ones(4), surface) is color


@pytest.mark.parametrize("method", ["banded", "full"])
def test_views_add_the_fine_residual(method):
    K = pinhole(32, 24, 16.0)
    plain = MapSet(CONFIG, [exact_submap(patch(-2, 2), plane_z(0.13))])
    fine = MapSet(CONFIG, [_shifted(exact_submap(patch(-2, 2), plane_z(0.13)), -0.1)])
    a = render_view(plain, np.eye(4), K, 32, 24, method=method)
    b = render_view(fine, np.eye(4), K, 32, 24, method=method)
    assert a.valid.any()
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_allclose(b.rgb[a.valid], np.clip(a.rgb[a.valid] - 0.1, 0, 1), atol=1e-5)


def test_mesh_vertex_colours_add_the_fine_residual():
    plain = extract_submap_mesh(exact_submap(patch(-2, 3), plane_z(0.1)), 4)
    fine = extract_submap_mesh(_shifted(exact_submap(patch(-2, 3), plane_z(0.1)), -0.2), 4)
    np.testing.assert_array_equal(plain.vertices, fine.vertices)
    expected = np.clip(plain.visual.vertex_colors[:, :3].astype(int) - 51, 0, 255)  # 0.2 of 255
    assert np.abs(fine.visual.vertex_colors[:, :3].astype(int) - expected).max() <= 1


def test_checkpoint_keeps_the_fine_level_and_old_checkpoints_load_without_it(tmp_path):
    config = apply_overrides(CONFIG, {"fine_color": {"levels": 3, "table_log2": 8}})
    submap = exact_submap(patch(-2, 2), plane_z(0.13))
    submap.fine = FineColor(replace(FINE, finest=0.01), seed=5)
    loaded = load_checkpoint(save_checkpoint(MapSet(config, [submap]), tmp_path / "map.pt")).maps[0]
    assert torch.equal(loaded.fine.tables, submap.fine.tables)
    torch.testing.assert_close(loaded.fine.cells, submap.fine.cells)  # the stored levels, not the config's
    points = torch.rand(20, 3)
    torch.testing.assert_close(loaded.fine(points), submap.fine(points))
    # Written before levels had tables of their own sizes: one (L, T, F) tensor.
    payload = torch.load(tmp_path / "map.pt", weights_only=True)
    state = payload["maps"][0]["fine"]
    state["tables"] = state["tables"].reshape(3, 256, 2)
    del state["rows"]
    torch.save(payload, tmp_path / "levels.pt")
    torch.testing.assert_close(load_checkpoint(tmp_path / "levels.pt").maps[0].fine(points), submap.fine(points))
    # Tables of unequal sizes come back with their sizes, whatever the config says.
    submap.fine = FineColor(BY_SURFACE, seed=6)
    loaded = load_checkpoint(save_checkpoint(MapSet(config, [submap]), tmp_path / "surface.pt")).maps[0]
    assert loaded.fine.rows.tolist() == [16, 64, 256]
    torch.testing.assert_close(loaded.fine(points), submap.fine(points))
    # A checkpoint written before the level existed has no "fine" entry: no fine level.
    payload = torch.load(tmp_path / "map.pt", weights_only=True)
    del payload["maps"][0]["fine"]
    torch.save(payload, tmp_path / "old.pt")
    old = load_checkpoint(tmp_path / "old.pt")
    assert old.maps[0].fine is None
    assert render_view(old, np.eye(4), pinhole(32, 24, 16.0), 32, 24).valid.any()


@pytest.mark.parametrize("config", [FINE, BY_SURFACE], ids=["equal", "surface"])
def test_the_numba_features_match_the_torch_path(config):
    from slam.kernels import numba_kernels

    if numba_kernels() is None:
        pytest.skip("numba unavailable")
    from slam.fine_color import HASH_PRIMES
    from slam.kernels.fused import hash_grid

    fine = FineColor(config, seed=1)
    with torch.no_grad():
        fine.tables.normal_()
    points = (torch.rand(300, 3) - 0.5) * 6.0
    torch.testing.assert_close(hash_grid(points, fine.cells, fine.tables, fine.rows, HASH_PRIMES),
                               hash_features(points, fine.tables, fine.cells, fine.rows), atol=1e-5, rtol=1e-5)
    with torch.no_grad():  # the forward takes the kernel without gradients
        torch.testing.assert_close(fine(points), fine.head(hash_features(points, fine.tables, fine.cells, fine.rows)),
                                   atol=1e-5, rtol=1e-5)


def test_run_json_counts_the_fine_level_in_the_map_memory(tmp_path):
    import json

    from slam.runtime import run_slam

    base = preset("test")
    config = replace(apply_overrides(base, {"fine_color": {"levels": 2, "table_log2": 8}}),
                     runtime=replace(base.runtime, processes=False))
    frames = list(open_sequence("synthetic:orbit?frames=100&width=40&height=30", max_frames=2))
    assert run_slam([frames], config, tmp_path).status == "finished"
    memory = json.loads((tmp_path / "run.json").read_text())["map_memory_mb"]
    fine = load_checkpoint(tmp_path / "map.pt").maps[0].fine
    assert fine is not None and memory["fine_color"] == pytest.approx(fine.num_bytes() / 2**20)


def test_coarse_surface_is_the_view_without_the_fine_level():
    K = pinhole(32, 24, 16.0)
    submap = _shifted(exact_submap(patch(-2, 2), plane_z(0.13)), -0.1)
    view = render_view(MapSet(CONFIG, [exact_submap(patch(-2, 2), plane_z(0.13))]), np.eye(4), K, 32, 24)
    color, points, surface = coarse_surface(submap, torch.eye(4), torch.as_tensor(K, dtype=torch.float32), 32, 24,
                                            CONFIG)
    np.testing.assert_array_equal(surface.numpy(), view.valid.reshape(-1))
    np.testing.assert_allclose(color[surface].numpy(), view.rgb.reshape(-1, 3)[view.valid.reshape(-1)], atol=1e-5)
    # each point is its pixel's ray at the rendered z-depth
    np.testing.assert_allclose(points[surface, 2].numpy(), view.depth.reshape(-1)[view.valid.reshape(-1)], atol=1e-5)


def test_the_rendered_surface_fit_brings_views_at_the_keyframes_closer_to_the_input():
    # tables big enough that the 2 keyframes' cells rarely share a row (FINE's 2^8 rows would)
    mapper = _mapped(3, surface="rendered", fine=replace(FINE, table_log2=14, final_fit_iterations=40))
    mapset = mapper.maps
    errors = {}
    for label in ("fine", "coarse"):
        if label == "coarse":
            mapset.maps[0].fine = None
        total = 0.0
        for frame in _frames():
            view = render_view(mapset, frame.T_world_cam_gt, frame.K.numpy(), frame.width, frame.height)
            total += float(np.abs(view.rgb - frame.rgb.numpy())[view.valid].mean())
        errors[label] = total
    assert errors["fine"] < 0.8 * errors["coarse"], errors


@pytest.mark.parametrize("block", [1, 2])
def test_the_rendered_surface_fit_learns_from_blocks_of_the_keyframe(block):
    """``fit_render_block`` b: one fit point per b x b block of a keyframe's pixels, its
    colour the block's mean."""
    mapper = _mapped(2, surface="rendered", fine=replace(FINE, fit_render_block=block))
    submap = mapper.maps.maps[0]
    frame = submap.keyframes[0].frame
    points, residual = mapper._rendered_residuals(submap, submap.keyframes[:1])
    assert points.shape == residual.shape and points.shape[1] == 3
    blocks = (frame.height // block) * (frame.width // block)
    assert 0.5 * blocks < points.shape[0] <= blocks


def test_the_rendered_surface_fit_learns_from_observed_pixels_without_depth_too():
    """``fit_pixels`` "observed": every keyframe pixel whose colour was observed counts (the fit
    reads the rendered surface, not the depth); "measured": only those with depth. Pixels
    off the raw image (``color_valid`` False) count in neither."""
    from slam.mapping import fit_pixels

    mapper = _mapped(2, surface="rendered", fine=replace(FINE, fit_pixels="measured"))
    submap = mapper.maps.maps[0]
    keyframe = submap.keyframes[0]
    frame = keyframe.frame
    no_depth = torch.zeros_like(frame.depth, dtype=torch.bool)
    no_depth[:, : frame.width // 2] = True  # the left half lost its depth, as Kinect's shadows do
    seen = torch.ones_like(no_depth)
    seen[: frame.height // 4] = False  # the top quarter lay off the raw image
    keyframe.frame = replace(frame, depth=torch.where(no_depth, 0.0, frame.depth), color_valid=seen)
    counted = {}
    for which in ("measured", "observed"):
        mapper.config = replace(mapper.config, fine_color=replace(mapper.config.fine_color, fit_pixels=which))
        pixels = fit_pixels(keyframe.frame, which)
        counted[which] = mapper._rendered_residuals(submap, [keyframe])[0].shape[0]
        assert counted[which] <= int(pixels.sum())
    assert not fit_pixels(keyframe.frame, "measured")[:, : frame.width // 2].any()
    assert torch.equal(fit_pixels(keyframe.frame, "observed"), seen)
    assert counted["observed"] > 1.3 * counted["measured"], counted  # 3/4 of the rows against 1/2 of the columns
    # Without a mask (a stream's frames): every pixel but those black without depth.
    black = replace(frame, rgb=torch.where(no_depth[..., None] & seen[..., None].logical_not(), 0.0, frame.rgb),
                    depth=torch.where(no_depth, 0.0, frame.depth), color_valid=None)
    assert torch.equal(fit_pixels(black, "observed"), ~(no_depth & ~seen))
    assert torch.equal(fit_pixels(replace(frame, color_valid=None), "observed"), torch.ones_like(no_depth))
