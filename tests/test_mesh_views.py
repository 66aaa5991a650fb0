"""Meshes and whole-image rendering of the neural map (slam.mesh, slam.views).

Two kinds of maps: *exact* maps whose decoder is wired by hand so that the SDF is the
trilinear interpolation of one embedding channel (a plane is then reproduced exactly), and a
map *fitted* to an analytic wall-and-floor scene. The fit regresses the SDF and colour at
random points of the allocated voxels, the targets the rendering losses drive the map
towards; it is ~20x cheaper than training through the renderer and keeps this file fast.
"""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest
import torch
import trimesh

from slam.config import preset
from slam.maps import MapSet, SubMap
from slam.mesh import empty_mesh, export_mesh, extract_mesh, extract_submap_mesh, mesh_to_bytes
from slam.render import camera_rays, interpolate_embeddings, rays_in_map
from slam.views import (RenderedView, fused_linear_available, band_chunks, band_sample_counts, coarse_grid, depth_bands, planar_depths,
                        rays_near_surface, render_view)
from slam.voxels import morton_decode

CONFIG = preset("test")
VOXEL = CONFIG.voxel.voxel_size
TRUNCATION = CONFIG.render.truncation


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    """Run this module's tiny tensors on one thread, then restore the setting.

    Threads gain nothing at these sizes, and on a busy shared 2-core machine torch's
    spinning worker threads made this file ten times slower (seconds -> a minute).
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# --------------------------------------------------------------- exact maps
def _linear_layers(module: torch.nn.Module) -> list[torch.nn.Linear]:
    return [m for m in module.modules() if isinstance(m, torch.nn.Linear)]


def wire_decoder(decoder) -> None:
    """Make ``decoder`` output SDF = emb[0] and RGB = sigmoid(8 emb[1:4] - 4) exactly.

    The shared ReLU layers carry (emb0, -emb0, emb1, emb2, emb3) through as identities
    (emb1..3 must be >= 0); the SDF head subtracts the two signed copies.
    """
    with torch.no_grad():
        for p in decoder.parameters():
            p.zero_()
        trunk = _linear_layers(decoder.trunk)
        trunk[0].weight[0, 0], trunk[0].weight[1, 0] = 1.0, -1.0
        for c in range(3):
            trunk[0].weight[2 + c, 1 + c] = 1.0
        for layer in trunk[1:]:
            for i in range(5):
                layer.weight[i, i] = 1.0
        head = decoder.sdf_head
        head.weight[0, 0], head.weight[0, 1] = 1.0, -1.0
        for c in range(3):
            head.weight[1 + c, 2 + c] = 1.0
        color = _linear_layers(decoder.color_head)
        for layer in color[:-1]:
            for c in range(3):
                layer.weight[c, c] = 1.0
        for c in range(3):
            color[-1].weight[c, c] = 8.0
            color[-1].bias[c] = -4.0


def exact_submap(voxels_ijk, sdf_metres, *, map_id: int = 0,
                 T_world_map: torch.Tensor | None = None) -> SubMap:
    """A submap over the given voxels whose SDF is ``sdf_metres(points)`` at the corners.

    voxels_ijk: list of (i, j, k); sdf_metres: (N, 3) map-frame points -> (N,) metres.
    Colour channels vary smoothly with position.
    """
    submap = SubMap.create(map_id, 0, CONFIG, torch.device("cpu"), T_world_map=T_world_map)
    centres = (torch.tensor(voxels_ijk, dtype=torch.float32) + 0.5) * VOXEL
    submap.voxels.allocate(centres)
    corners = morton_decode(submap.voxels.corner_codes).to(torch.float32) * VOXEL
    values = torch.zeros(corners.shape[0], submap.voxels.embed_dim)
    values[:, 0] = sdf_metres(corners) / TRUNCATION
    values[:, 1] = 0.5 + 0.4 * torch.sin(3.0 * corners[:, 0])
    values[:, 2] = 0.5 + 0.4 * torch.cos(2.0 * corners[:, 1])
    values[:, 3] = 0.5 + 0.4 * torch.sin(5.0 * corners[:, 0] + corners[:, 1])
    with torch.no_grad():
        submap.voxels.embeddings[submap.voxels.corner_rows] = values
    wire_decoder(submap.decoder)
    return submap


def plane_z(z0: float):
    """SDF of the half-space z < z0 being free (a wall facing -z at z0), in metres."""
    return lambda p: z0 - p[:, 2]


def patch(lo: int, hi: int, k: int = 0, hole: tuple[int, int] | None = None) -> list[tuple[int, int, int]]:
    """Voxels (i, j, k) for i, j in [lo, hi), without the ``hole`` column."""
    return [(i, j, k) for i in range(lo, hi) for j in range(lo, hi) if (i, j) != hole]


def translation(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> torch.Tensor:
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([x, y, z])
    return T


def pinhole(width: int, height: int, focal: float) -> np.ndarray:
    return np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])


# ------------------------------------------------------------ exact meshes
def test_plane_mesh_is_exact_and_only_inside_allocated_voxels():
    submap = exact_submap(patch(0, 3, hole=(1, 1)), plane_z(0.13))
    mesh = extract_submap_mesh(submap, 4)
    assert len(mesh.faces) > 0
    np.testing.assert_allclose(mesh.vertices[:, 2], 0.13, atol=1e-5)
    # 8 of the 3x3 voxels, each covered completely: nothing lost at edges, nothing added.
    assert mesh.area == pytest.approx(8 * VOXEL**2, rel=1e-5)
    centres = mesh.triangles_center
    in_hole = (np.abs(centres[:, 0] - 0.3) < 0.1) & (np.abs(centres[:, 1] - 0.3) < 0.1)
    assert not in_hole.any()
    # Normals point to free space (towards the cameras), as renderers expect.
    assert (mesh.face_normals[:, 2] < -0.99).all()


def test_no_surface_in_voxels_the_mapper_never_optimised():
    submap = exact_submap(patch(0, 3), plane_z(0.13))
    full_area = extract_submap_mesh(submap, 4).area
    counts = torch.ones(submap.voxels.num_corners, dtype=torch.int32)
    v = submap.voxels
    # Voxel 0 is (0, 0, 0), the patch's corner: its corner 0 belongs to no other voxel.
    assert morton_decode(v.voxel_codes[:1]).tolist() == [[0, 0, 0]]
    counts[v.voxel_corners[0, 0]] = 0
    submap.corner_updates = counts
    lost = int((~submap.optimised_voxels(1)).sum())
    assert lost == 1
    assert extract_submap_mesh(submap, 4).area == pytest.approx(full_area * 8 / 9, rel=1e-5)
    assert extract_submap_mesh(submap, 4, min_corner_updates=0).area == pytest.approx(full_area, rel=1e-6)


def test_surface_only_keeps_the_voxels_that_held_observed_depth():
    submap = exact_submap(patch(0, 3), plane_z(0.13))
    full_area = extract_submap_mesh(submap, 4).area
    v = submap.voxels
    submap.observe_surface(v.voxel_codes[:4])
    assert bool(submap.surface_voxels()[:4].all()) and not bool(submap.surface_voxels()[4:].any())
    assert extract_submap_mesh(submap, 4).area == pytest.approx(full_area * 4 / 9, rel=1e-5)
    assert extract_submap_mesh(submap, 4, surface_only=False).area == pytest.approx(full_area, rel=1e-6)


def test_no_surface_across_an_unallocated_gap():
    # The zero crossing x = 0.3 lies in voxel (1, 0, 0), which is not allocated: a dense
    # marching cubes over the bounding box would put a wall there.
    submap = exact_submap([(0, 0, 0), (2, 0, 0)], lambda p: 0.3 - p[:, 0])
    for resolution in (1, 4):
        assert len(extract_submap_mesh(submap, resolution).faces) == 0


def test_blocks_and_chunks_do_not_change_the_mesh():
    normal = torch.tensor([0.3, -0.5, 0.81])
    normal = normal / normal.norm()
    submap = exact_submap([(i, j, k) for i in range(-2, 3) for j in range(-2, 3) for k in range(-1, 2)],
                          lambda p: 0.05 - p @ normal)
    whole = extract_submap_mesh(submap, 3, block_voxels=16)
    pieces = extract_submap_mesh(submap, 3, block_voxels=1, chunk_points=50)
    assert len(whole.faces) > 50
    assert len(pieces.vertices) == len(whole.vertices)  # block seams merged
    assert len(pieces.faces) == len(whole.faces)
    assert pieces.area == pytest.approx(whole.area, rel=1e-6)
    np.testing.assert_allclose(whole.vertices @ normal.numpy().astype(np.float64), 0.05, atol=1e-5)
    edges = np.sort(whole.edges, axis=1)  # an open patch: no edge has more than 2 faces
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.max() <= 2


def test_vertex_colours_come_from_the_colour_head():
    submap = exact_submap(patch(-2, 3), plane_z(0.1))
    mesh = extract_submap_mesh(submap, 4)
    colors = np.asarray(mesh.visual.vertex_colors)
    assert colors.dtype == np.uint8 and colors.shape == (len(mesh.vertices), 4)
    assert (colors[:, :3].std(0) > 5).all()
    # Expected: the hand-wired head at the vertices (trilinear interpolation of the
    # corner channels, which are not linear in x, so compare loosely).
    p = mesh.vertices
    expected_r = 1 / (1 + np.exp(-(8 * (0.5 + 0.4 * np.sin(3 * p[:, 0])) - 4)))
    assert np.abs(colors[:, 0] / 255.0 - expected_r).max() < 0.06


def test_world_mesh_places_submaps_by_their_pose():
    yaw = np.pi / 2
    T = torch.tensor([[np.cos(yaw), -np.sin(yaw), 0, 1.0], [np.sin(yaw), np.cos(yaw), 0, -2.0],
                      [0, 0, 1, 0.5], [0, 0, 0, 1]], dtype=torch.float32)
    a = exact_submap(patch(0, 2), plane_z(0.1), map_id=0)
    b = exact_submap(patch(0, 2), plane_z(0.1), map_id=1, T_world_map=T)
    local = extract_submap_mesh(b, 2)
    world = extract_mesh(MapSet(CONFIG, [a, b]), resolution=2)
    assert len(world.faces) == 2 * len(local.faces)
    expected = local.vertices @ T[:3, :3].numpy().T.astype(np.float64) + T[:3, 3].numpy()
    np.testing.assert_allclose(world.vertices[len(local.vertices):], expected, atol=1e-6)
    assert len(extract_mesh(MapSet(CONFIG, [])).faces) == 0


def test_mesh_resolution_must_be_positive():
    submap = exact_submap(patch(0, 1), plane_z(0.1))
    with pytest.raises(ValueError, match="resolution"):
        extract_submap_mesh(submap, 0)


@pytest.mark.parametrize("fmt", ["ply", "glb", "obj"])
def test_export_round_trip(fmt, tmp_path):
    mesh = extract_submap_mesh(exact_submap(patch(0, 2), plane_z(0.1)), 2)
    data = export_mesh(mesh, fmt)
    assert isinstance(data, bytes) and data == mesh_to_bytes(mesh, fmt.upper())
    loaded = trimesh.load(io.BytesIO(data), file_type=fmt, force="mesh", process=False)
    assert len(loaded.faces) == len(mesh.faces)
    assert loaded.area == pytest.approx(mesh.area, rel=1e-5)
    if fmt == "ply":
        assert b"format binary_little_endian" in data[:200]
        np.testing.assert_array_equal(np.asarray(loaded.visual.vertex_colors), np.asarray(mesh.visual.vertex_colors))
    if fmt == "glb":
        assert data[:4] == b"glTF"
    path = export_mesh(mesh, tmp_path / f"m.{fmt}")
    assert path.read_bytes()[:4] == data[:4] and sorted(p.name for p in tmp_path.iterdir()) == [f"m.{fmt}"]
    with pytest.raises(ValueError, match="suffix"):
        export_mesh(mesh, tmp_path / "m.stl")
    assert len(export_mesh(empty_mesh(), fmt)) > 0  # a map with no surface yet still exports


# ------------------------------------------------------------- exact views
def test_rays_near_surface_example():
    sdf = torch.tensor([1.0, 0.3, -0.1, 1.0, 0.5, 0.4, -0.4])
    t = torch.tensor([0.0, 1.0, 2.0, 0.0, 1.0, 0.0, 1.0])
    rays = torch.tensor([0, 0, 0, 1, 1, 2, 2])
    assert rays_near_surface(sdf, t, rays, 4, 0.2, 1.5).tolist() == [True, False, True, False]


def test_rays_near_surface_ignores_a_sign_change_across_a_gap():
    # Ray 0: a steep crossing between neighbouring samples. Ray 1: the same values, but the
    # samples lie in two voxels 3 m apart (free space between): no surface there.
    sdf = torch.tensor([0.4, -0.4, 0.4, -0.4])
    t = torch.tensor([1.0, 1.02, 1.0, 4.0])
    rays = torch.tensor([0, 0, 1, 1])
    assert rays_near_surface(sdf, t, rays, 2, 0.2, 0.03).tolist() == [True, False]


def test_render_plane_depth_colour_and_empty_pixels():
    submap = exact_submap(patch(-3, 3), plane_z(0.13), T_world_map=translation(z=1.0))
    mapset = MapSet(CONFIG, [submap])
    K = pinhole(40, 30, 20.0)
    view = render_view(mapset, np.eye(4), K, 40, 30)
    assert isinstance(view, RenderedView)
    assert view.rgb.shape == (30, 40, 3) and view.rgb.dtype == np.float32
    assert view.depth.shape == (30, 40) and view.depth.dtype == np.float32
    # The patch spans x, y in [-0.6, 0.6] at z = 1.13: pixels with |u - 20| < 20 * 0.6 / 1.13.
    u = np.arange(40) + 0.5 - 20
    inside = np.abs(u) < 20 * 0.6 / 1.13 - 1
    outside = np.abs(u) > 20 * 0.6 / 1.13 + 1
    centre_rows = slice(10, 20)
    assert view.valid[centre_rows][:, inside].all()
    np.testing.assert_allclose(view.depth[centre_rows][:, inside], 1.13, atol=0.006)
    assert (view.depth[centre_rows][:, outside] == 0).all()
    assert (view.rgb[centre_rows][:, outside] == 0).all()
    assert (view.map_index[centre_rows][:, outside] == -1).all()
    assert view.rgb[view.valid].std(0).min() > 0.01
    # Chunking changes nothing; looking away sees nothing.
    chunked = render_view(mapset, torch.eye(4), torch.from_numpy(K), 40, 30, chunk_rays=97)
    np.testing.assert_allclose(chunked.depth, view.depth, atol=1e-5)
    behind = np.diag([-1.0, 1.0, -1.0, 1.0])
    away = render_view(mapset, behind, K, 40, 30)
    assert not away.valid.any() and (away.depth == 0).all() and (away.rgb == 0).all()


def test_compositing_takes_the_nearer_submap():
    far_map = exact_submap(patch(-3, 3), plane_z(0.13), map_id=0, T_world_map=translation(z=1.0))
    near_map = exact_submap(patch(-3, 3), plane_z(0.13), map_id=1, T_world_map=translation(x=0.5, z=0.6))
    K = pinhole(40, 30, 20.0)
    both = render_view(MapSet(CONFIG, [far_map, near_map]), np.eye(4), K, 40, 30)
    alone = [render_view(MapSet(CONFIG, [m]), np.eye(4), K, 40, 30) for m in (far_map, near_map)]
    assert (both.map_index == 0).sum() > 20 and (both.map_index == 1).sum() > 20
    np.testing.assert_allclose(both.depth[both.map_index == 0], 1.13, atol=0.006)
    np.testing.assert_allclose(both.depth[both.map_index == 1], 0.73, atol=0.006)
    # Where both see a surface the nearer one wins; elsewhere whichever sees one.
    depths = np.stack([np.where(v.valid, v.depth, np.inf) for v in alone])
    expected = np.where(np.isinf(depths.min(0)), 0, depths.min(0))
    np.testing.assert_allclose(both.depth, expected, atol=1e-6)
    assert (both.map_index[both.valid] == depths.argmin(0)[both.valid]).all()
    np.testing.assert_allclose(both.rgb[both.map_index == 1], alone[1].rgb[both.map_index == 1], atol=1e-6)


def test_render_view_rejects_bad_camera():
    mapset = MapSet(CONFIG, [exact_submap(patch(0, 1), plane_z(0.1))])
    with pytest.raises(ValueError, match="K"):
        render_view(mapset, np.eye(4), np.eye(4), 8, 8)
    with pytest.raises(ValueError, match="T_world_cam"):
        render_view(mapset, np.full((4, 4), np.nan), pinhole(8, 8, 8.0), 8, 8)
    with pytest.raises(ValueError, match="size"):
        render_view(mapset, np.eye(4), pinhole(8, 8, 8.0), 0, 8)


# -------------------------------------------------------------- fitted map
WALL_Z, FLOOR_Y = 2.95, 0.93  # not on voxel faces (0.2 m): the general case
SCENE_K = torch.tensor([[40.0, 0, 32], [0, 40.0, 24], [0, 0, 1]])
SCENE_SIZE = (64, 48)


def scene_sdf(p: torch.Tensor) -> torch.Tensor:
    """Free space is z < WALL_Z and y < FLOOR_Y (y points down). (N, 3) -> (N,) metres."""
    return torch.minimum(WALL_Z - p[:, 2], FLOOR_Y - p[:, 1])


def scene_color(p: torch.Tensor) -> torch.Tensor:
    return 0.5 + 0.4 * torch.stack([torch.sin(4 * p[:, 0]), torch.cos(3 * p[:, 1] + 2 * p[:, 2]),
                                    torch.sin(3 * p[:, 2] + p[:, 0])], -1)


def scene_depth(T_world_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays of every pixel and their analytic z-depth: origins, dirs (HW, 3), depth (HW,)."""
    width, height = SCENE_SIZE
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32), indexing="ij")
    origins, dirs = rays_in_map(T_world_cam, camera_rays(SCENE_K, torch.stack([u.flatten(), v.flatten()], -1)))
    t_wall = (WALL_Z - origins[:, 2]) / dirs[:, 2]
    down = dirs[:, 1] > 1e-6
    t_floor = torch.where(down, (FLOOR_Y - origins[:, 1]) / dirs[:, 1].clamp(min=1e-6), torch.full_like(t_wall, 1e9))
    return origins, dirs, torch.minimum(t_wall, t_floor)


def moved_camera() -> torch.Tensor:
    yaw = 0.1
    T = torch.eye(4)
    T[:3, :3] = torch.tensor([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    T[:3, 3] = torch.tensor([0.1, -0.05, 0.2])
    return T


def fit_scene(iterations: int = 300, batch: int = 1024, seed: int = 0) -> MapSet:
    """A test-preset submap fitted to the wall-and-floor scene seen from the identity camera."""
    torch.manual_seed(seed)
    submap = SubMap.create(0, 0, CONFIG, torch.device("cpu"), seed=seed)
    origins, dirs, depth = scene_depth(torch.eye(4))
    for offset in (-0.1, 0.0, 0.1):  # the surface voxels and their neighbours along the rays
        submap.voxels.allocate(origins + dirs * (depth + offset)[:, None])
    ijk = morton_decode(submap.voxels.voxel_codes).to(torch.float32)
    optimizer = torch.optim.Adam([{"params": [submap.voxels.embeddings], "lr": 2e-2},
                                 {"params": submap.decoder.parameters(), "lr": 1e-2}])
    for _ in range(iterations):
        voxel = torch.randint(0, ijk.shape[0], (batch,))
        points = (ijk[voxel] + torch.rand(batch, 3)) * VOXEL
        target = (scene_sdf(points) / TRUNCATION).clamp(-1.0, 1.0)
        sdf, feature = submap.decoder.sdf_and_feature(interpolate_embeddings(points, voxel, submap.view()))
        band = target.abs() < 1.0
        rgb = submap.decoder.color(feature[band])
        loss = ((sdf - target) ** 2).mean() + (rgb - scene_color(points[band])).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return MapSet(CONFIG, [submap])


@pytest.fixture(scope="module")
def fitted() -> MapSet:
    return fit_scene()


@pytest.mark.parametrize("camera", ["trained", "moved"])
def test_fitted_map_renders_the_analytic_depth(fitted, camera):
    T = torch.eye(4) if camera == "trained" else moved_camera()
    view = render_view(fitted, T, SCENE_K, *SCENE_SIZE)
    _, _, depth = scene_depth(T)
    truth = depth.reshape(SCENE_SIZE[1], SCENE_SIZE[0]).numpy()
    assert view.valid.mean() > (0.99 if camera == "trained" else 0.85)
    error = np.abs(view.depth - truth)[view.valid]
    assert np.median(error) < 0.008  # test preset: 4 cm steps bias the weighted depth by mm
    # The few larger errors sit on the wall-floor corner, where rays graze the floor.
    assert (error < 0.02).mean() > 0.95
    origins, dirs, _ = scene_depth(T)
    colour = scene_color(origins + dirs * depth[:, None]).reshape(SCENE_SIZE[1], SCENE_SIZE[0], 3).numpy()
    assert np.abs(view.rgb - colour)[view.valid].mean() < 0.1


def test_fitted_map_mesh_lies_on_the_planes(fitted):
    mesh = extract_mesh(fitted, resolution=4)
    distance = np.minimum(np.abs(mesh.vertices[:, 2] - WALL_Z), np.abs(mesh.vertices[:, 1] - FLOOR_Y))
    assert len(mesh.faces) > 1000
    assert np.median(distance) < 0.005 and np.percentile(distance, 95) < 0.015
    # Every face lies in an allocated voxel, and on the zero set of the renderer's SDF.
    submap = fitted.maps[0]
    points = torch.tensor(mesh.triangles_center, dtype=torch.float32)
    voxel = submap.voxels.find_voxels(points)
    assert (voxel >= 0).all()
    with torch.no_grad():
        sdf, _ = submap.decoder.sdf_and_feature(interpolate_embeddings(points, voxel, submap.view()))
    assert np.median(np.abs(sdf.numpy())) * TRUNCATION < 0.002
    colors = np.asarray(mesh.visual.vertex_colors)
    assert colors.dtype == np.uint8 and (colors[:, :3].std(0) > 20).all()


def test_higher_resolution_gives_a_finer_mesh(fitted):
    coarse = extract_mesh(fitted, resolution=2)
    fine = extract_mesh(fitted, resolution=4)
    assert len(fine.faces) > 3 * len(coarse.faces)
    assert fine.area == pytest.approx(coarse.area, rel=0.05)


def test_config_resolution_is_the_default(fitted):
    config = dataclasses.replace(CONFIG, mesh=dataclasses.replace(CONFIG.mesh, resolution=2))
    default = extract_mesh(MapSet(config, fitted.maps))
    assert len(default.faces) == len(extract_mesh(fitted, resolution=2).faces)


# ------------------------------------------------------------ banded views
def test_coarse_grid_keeps_the_last_pixel():
    assert coarse_grid(10, 4).tolist() == [0, 4, 8, 9]
    assert coarse_grid(9, 4).tolist() == [0, 4, 8]
    assert coarse_grid(1, 4).tolist() == [0]


def test_depth_bands_span_the_coarse_neighbours():
    # A 3 x 3 coarse grid over a 9 x 9 image (stride 4): one cell sees nothing.
    cu = cv = coarse_grid(9, 4)
    depth = torch.tensor([[1.0, 2.0, 3.0], [1.0, 0.0, 3.0], [1.0, 2.0, 3.0]])
    surface = depth > 0
    lo, hi = depth_bands(depth, surface, cu, cv, 9, 9)
    lo, hi = lo.reshape(9, 9), hi.reshape(9, 9)
    assert lo.min() == 1.0 and hi.max() == 3.0 and torch.isfinite(lo).all()
    # Nothing seen anywhere: every band is empty.
    lo, _ = depth_bands(depth, torch.zeros_like(surface), cu, cv, 9, 9)
    assert torch.isinf(lo).all()


def _plane_depth(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """z-depth of a tilted plane seen by a pinhole camera: 1/z is affine in (u, v)."""
    return 1.0 / (0.5 + 0.01 * u + 0.004 * v)


def test_planar_depths_are_exact_on_a_plane():
    cu, cv = coarse_grid(13, 4), coarse_grid(10, 4)  # [0, 4, 8, 12] and [0, 4, 8, 9]
    coarse = _plane_depth(cu[None, :].double(), cv[:, None].double())
    depth, off_plane = planar_depths(coarse, torch.ones_like(coarse, dtype=torch.bool), cu, cv, 13, 10)
    u, v = torch.meshgrid(torch.arange(13.0), torch.arange(10.0), indexing="xy")
    # Linear interpolation of z itself would err by ~1 mm here; of 1/z, by rounding only.
    torch.testing.assert_close(depth, _plane_depth(u.double(), v.double()).reshape(-1), rtol=1e-12, atol=1e-12)
    assert off_plane.reshape(10, 13)[0:4, 4:8].isinf().all()  # the grid's edge: nothing to check
    # A cell whose corners have neighbours both ways, evenly spaced: nothing off the plane.
    grid = torch.arange(0, 17, 4)
    coarse = _plane_depth(grid[None, :].double(), grid[:, None].double())
    _, off_plane = planar_depths(coarse, torch.ones_like(coarse, dtype=torch.bool), grid, grid, 17, 17)
    assert off_plane.reshape(17, 17)[4:12, 4:12].max() < 1e-12


def test_planar_depths_flag_an_edge_and_a_missing_sample():
    cu = cv = coarse_grid(17, 4)  # a 5 x 5 coarse grid
    flat = torch.ones(5, 5)
    _, off_plane = planar_depths(flat, flat > 0, cu, cv, 17, 17)
    assert off_plane.reshape(17, 17)[6, 6] == 0.0  # inside a flat grid
    assert torch.isinf(off_plane.reshape(17, 17)[1, 6])  # the grid's edge: no neighbour to check
    # A crease along a cell's edge (rows 0-2 at 1 m, 3-4 at 2 m): the cell above it has no
    # twist, but its lower corners bend.
    crease = torch.where(torch.arange(5)[:, None] < 3, 1.0, 2.0).expand(5, 5)
    _, off_plane = planar_depths(crease, crease > 0, cu, cv, 17, 17)
    assert off_plane.reshape(17, 17)[10, 6] > 0.1
    # A corner that saw nothing.
    missing = flat.clone()
    missing[2, 2] = 0.0
    _, off_plane = planar_depths(missing, missing > 0, cu, cv, 17, 17)
    assert torch.isinf(off_plane.reshape(17, 17)[6, 6])


def test_band_chunks_cover_every_ray_in_bounded_runs():
    assert band_chunks(torch.tensor([3, 3, 3, 9, 1]), 6) == [(0, 2), (2, 3), (3, 4), (4, 5)]
    assert band_chunks(torch.tensor([2, 2, 2]), 6) == [(0, 3)]  # an exact fit stays one run
    assert band_chunks(torch.tensor([0, 0, 5]), 4) == [(0, 2), (2, 3)]  # a long ray runs alone
    assert band_chunks(torch.zeros(0, dtype=torch.long), 4) == []
    counts = torch.randint(0, 12, (500,), generator=torch.Generator().manual_seed(0))
    runs = band_chunks(counts, 40)
    assert runs[0][0] == 0 and runs[-1][1] == 500
    assert all(a[1] == b[0] for a, b in zip(runs, runs[1:]))
    assert all(int(counts[s:e].sum()) <= 40 or e - s == 1 for s, e in runs)


def test_band_sample_counts_count_the_grid_points_in_the_band():
    near = torch.tensor([0.0, 0.31, 1.05, 2.0, 0.5])
    far = torch.tensor([0.5, 0.49, 1.05, 1.0, 0.51])
    step = 0.1
    # Grid t = (k + 1/2) step in [near, far): 0.05 .. 0.45; 0.35, 0.45; none; none; none.
    expected = [int(((torch.arange(40) + 0.5) * step >= n).logical_and((torch.arange(40) + 0.5) * step < f).sum())
                for n, f in zip(near.tolist(), far.tolist())]
    assert band_sample_counts(near, far, step).tolist() == expected == [5, 2, 0, 0, 0]


def test_banded_view_does_not_depend_on_the_chunk_size(fitted):
    """The band pass runs in sample-bounded runs of the chunk: any chunk size gives the same
    image."""
    T = moved_camera()
    big = render_view(fitted, T, SCENE_K, *SCENE_SIZE, method="banded")
    small = render_view(fitted, T, SCENE_K, *SCENE_SIZE, method="banded", chunk_rays=7)
    assert (big.valid == small.valid).all()
    np.testing.assert_allclose(small.depth, big.depth, atol=1e-5)
    np.testing.assert_allclose(small.rgb, big.rgb, atol=1e-5)


@pytest.mark.parametrize("camera", ["trained", "moved"])
def test_planar_bands_change_little_on_the_fitted_map(fitted, camera):
    """The banded view with bands centred on the planar interpolation against the plain
    bands, on the wall and floor: the same pixels, the same depths to a millimetre."""
    T = torch.eye(4) if camera == "trained" else moved_camera()
    plain = render_view(fitted, T, SCENE_K, *SCENE_SIZE, method="banded", planar_tolerance=0.0)
    planar = render_view(fitted, T, SCENE_K, *SCENE_SIZE, method="banded", planar_tolerance=0.01)
    assert (plain.valid != planar.valid).mean() < 0.005
    both = plain.valid & planar.valid
    assert np.abs(planar.depth[both] - plain.depth[both]).max() < 1e-3


@pytest.mark.parametrize("camera", ["trained", "moved"])
def test_banded_view_matches_the_full_render(fitted, camera):
    """The fast path gives the reference's pixels: the same samples near the first crossing
    less the far, light ones, so depth agrees within an eighth of the test preset's 4 cm step
    but on a few pixels of the crease and silhouettes (fits of seeds 0-4: 0.5-1.5 % of pixels
    beyond 5 mm, none beyond 15 mm; the 99th percentile 3.8-5.8 mm), colour within a few
    levels, and coverage but for a few pixels on silhouettes."""
    T = torch.eye(4) if camera == "trained" else moved_camera()
    full = render_view(fitted, T, SCENE_K, *SCENE_SIZE, method="full")
    banded = render_view(fitted, T, SCENE_K, *SCENE_SIZE, method="banded", coarse_stride=4)
    both = full.valid & banded.valid
    assert both.sum() > 0.8 * full.valid.sum()
    assert (full.valid != banded.valid).mean() < 0.01
    depth_error = np.abs(banded.depth[both] - full.depth[both])
    assert (depth_error > 5e-3).mean() < 0.025 and depth_error.max() < 0.02 and np.median(depth_error) < 1e-3
    rgb_error = np.abs(banded.rgb[both] - full.rgb[both])
    assert rgb_error.mean() < 0.01 and np.percentile(rgb_error, 99) < 0.05
    assert (banded.map_index[both] == full.map_index[both]).all()


def test_banded_view_composites_submaps_like_the_full_render():
    far_map = exact_submap(patch(-3, 3), plane_z(0.13), map_id=0, T_world_map=translation(z=1.0))
    near_map = exact_submap(patch(-3, 3), plane_z(0.13), map_id=1, T_world_map=translation(x=0.5, z=0.6))
    mapset, K = MapSet(CONFIG, [far_map, near_map]), pinhole(40, 30, 20.0)
    full = render_view(mapset, np.eye(4), K, 40, 30, method="full")
    banded = render_view(mapset, np.eye(4), K, 40, 30)
    assert (full.map_index != banded.map_index).mean() < 0.02
    same = full.map_index == banded.map_index
    np.testing.assert_allclose(banded.depth[same], full.depth[same], atol=5e-3)
    with pytest.raises(ValueError, match="method"):
        render_view(mapset, np.eye(4), K, 40, 30, method="fast")
    with pytest.raises(ValueError, match="coarse_stride"):
        render_view(mapset, np.eye(4), K, 40, 30, coarse_stride=0)
    with pytest.raises(ValueError, match="planar_tolerance"):
        render_view(mapset, np.eye(4), K, 40, 30, planar_tolerance=-0.01)
    with pytest.raises(ValueError, match="precision"):
        render_view(mapset, np.eye(4), K, 40, 30, precision="float16")


@pytest.mark.skipif(not fused_linear_available(), reason="needs oneDNN's fused linear and native bfloat16")
@pytest.mark.parametrize("color_layers", [0, 2])
def test_fused_bfloat16_decoder_matches_its_plain_twin(color_layers):
    """The fused path (one oneDNN call a layer, the feature rows and the colour head's first
    layer multiplied into one) gives the plain bfloat16 layers' SDF and colour, and the float32
    decoder's within bfloat16's rounding."""
    from slam.decoder import Decoder
    from slam.views import Bfloat16Decoder

    torch.manual_seed(0)
    decoder = Decoder(dataclasses.replace(preset("cpu").decoder, color_layers=color_layers), 16)
    emb = torch.randn(5000, 16)
    with torch.no_grad():
        exact_sdf, exact_hidden = decoder.sdf_and_hidden(emb)
        exact_rgb = decoder.color(decoder.feature_from_hidden(exact_hidden))
        outputs = []
        for fused in (True, False):
            twin = Bfloat16Decoder(decoder, fused=fused)
            sdf, hidden = twin.sdf_and_hidden(emb)
            outputs.append((sdf, twin.color_from_hidden(hidden)))
    (fused_sdf, fused_rgb), (plain_sdf, plain_rgb) = outputs
    assert fused_sdf.dtype == fused_rgb.dtype == torch.float32 and fused_rgb.shape == (5000, 3)
    scale = exact_sdf.abs().max()
    assert (fused_sdf - plain_sdf).abs().max() < 0.02 * scale
    assert (fused_sdf - exact_sdf).abs().max() < 0.02 * scale
    assert (fused_rgb - plain_rgb).abs().max() < 0.01 and (fused_rgb - exact_rgb).abs().mean() < 2e-3


@pytest.mark.parametrize("method", ["banded", "full"])
def test_bfloat16_decoder_renders_the_float32_view(fitted, method):
    """The bfloat16 copy of the decoder (views only) moves depth by under a millimetre and
    colour by under a percent; the float32 decoder is left as it was."""
    decoder = fitted.maps[0].decoder
    before = {k: v.clone() for k, v in decoder.state_dict().items()}
    exact = render_view(fitted, moved_camera(), SCENE_K, *SCENE_SIZE, method=method, precision="float32")
    fast = render_view(fitted, moved_camera(), SCENE_K, *SCENE_SIZE, method=method, precision="bfloat16")
    both = exact.valid & fast.valid
    assert (exact.valid != fast.valid).mean() < 0.01
    assert np.percentile(np.abs(fast.depth[both] - exact.depth[both]), 99) < 1e-3
    assert np.abs(fast.rgb[both] - exact.rgb[both]).mean() < 0.01
    assert all(torch.equal(v, before[k]) and v.dtype == torch.float32 for k, v in decoder.state_dict().items())
