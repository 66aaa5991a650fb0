"""Tests for ar/: rasteriser against a ray-casting reference, footprint/depth/shading golden
values, anti-aliasing, depth-tested compositing, occlusion IoU, assets and the object spec."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

import ar
from ar import (
    AssetError,
    Light,
    ObjectMesh,
    ObjectSpecError,
    VirtualObject,
    composite,
    composite_layer,
    load_asset,
    load_objects_json,
    make_shape,
    mask_iou,
    rasterize_objects,
    rasterize_triangles,
    render_objects,
)
from ar.objects import SHAPES
from ar.reference import composite_reference, raycast_triangles_reference


def pinhole(f: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def pose(rotation: np.ndarray | None = None, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = rotation
    T[:3, 3] = translation
    return T


def rot_y(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def random_triangles(rng: np.random.Generator, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Triangles in front of, around and crossing the near plane, with random corner colours."""
    tri = rng.uniform(-1.0, 1.0, (count, 3, 3))
    tri[..., 2] = rng.uniform(-0.5, 3.0, (count, 3))
    return tri, rng.uniform(0.0, 1.0, (count, 3, 3)).astype(np.float32)


# ---------------------------------------------------------------------------------------
# Rasteriser against the plain ray-casting reference.


@pytest.mark.parametrize("seed, supersample", [(0, 1), (1, 2), (2, 1), (3, 3)])
def test_rasteriser_matches_raycast_reference(seed: int, supersample: int, device: str) -> None:
    rng = np.random.default_rng(seed)
    tri, rgb = random_triangles(rng, 8)
    width, height = 48 // supersample, 36 // supersample  # the reference is slow: ~1700 samples
    K = pinhole(45.0 / supersample, width / 2 - 0.3, height / 2 - 0.8)
    layer = rasterize_triangles(tri, rgb, K, width, height, supersample=supersample, z_near=0.1, device=device)
    depth, color = layer.dense()
    ref_depth, ref_color = raycast_triangles_reference(tri, rgb, K, width, height, supersample=supersample, z_near=0.1)

    covered, ref_covered = np.isfinite(depth), np.isfinite(ref_depth)
    assert ref_covered.sum() > 300, "the random scene should cover a good part of the image"
    # Samples lying within rounding of an edge may go either way; there are next to none.
    assert (covered != ref_covered).sum() <= 2
    both = covered & ref_covered
    np.testing.assert_allclose(depth[both], ref_depth[both], rtol=1e-5)
    color_error = np.abs(color[both] - ref_color[both]).max(axis=-1)
    assert (color_error > 1e-4).sum() <= 2  # ties where two triangles cross
    assert (depth[covered] >= 0.1 - 1e-6).all()


def test_near_plane_clips_a_floor_under_the_camera() -> None:
    """A floor 0.5 m below the camera running from behind it to 10 m ahead: every pixel below
    the horizon sees it at z = 0.5 f / (v - cy), nothing is drawn above."""
    floor = np.array([[[-10, 0.5, -1], [10, 0.5, -1], [10, 0.5, 10]], [[-10, 0.5, -1], [10, 0.5, 10], [-10, 0.5, 10]]])
    K = pinhole(40.0, 31.5, 23.5)
    layer = rasterize_triangles(floor, np.ones((2, 3, 3), np.float32), K, 64, 48, z_near=0.05)
    depth, _ = layer.dense()
    rows = np.arange(48)[:, None] - 23.5
    with np.errstate(divide="ignore"):
        expected = np.where(rows > 0, 0.5 * 40.0 / rows, np.inf) * np.ones((1, 64))
    expected[expected > 10] = np.inf  # beyond the far edge of the floor
    np.testing.assert_array_equal(np.isfinite(depth), np.isfinite(expected))
    np.testing.assert_allclose(depth[np.isfinite(depth)], expected[np.isfinite(expected)], rtol=1e-5)


def test_camera_inside_a_cube_sees_its_inner_faces() -> None:
    cube = VirtualObject(make_shape("cube"), pose(), scale=2.0)
    render = render_objects([cube], pinhole(30.0, 31.5, 23.5), pose(), 64, 48)
    assert (render.coverage == 1.0).all()
    centre = render.depth[22:26, 30:34]
    np.testing.assert_allclose(centre, 1.0, rtol=1e-5)  # the wall straight ahead is 1 m away
    assert (render.depth <= 1.0 + 1e-5).all()


# ---------------------------------------------------------------------------------------
# Golden footprint, depth, shading and anti-aliasing.


def test_cube_projects_to_the_right_footprint_and_depth() -> None:
    """A unit cube 3 m ahead: its front face (z = 2.5) spans 100 * 0.5 / 2.5 = 20 px each way
    from the centre; with cx = 31.5 its edges fall on pixel borders, so coverage is 0 or 1."""
    K = pinhole(100.0, 31.5, 23.5)
    cube = VirtualObject(make_shape("cube"), pose(translation=(0, 0, 3)), scale=1.0, color=(0.2, 0.6, 0.4))
    render = render_objects([cube], K, pose(), 64, 48, supersample=2)
    expected = np.zeros((48, 64), bool)
    expected[4:44, 12:52] = True
    np.testing.assert_array_equal(render.coverage, expected.astype(np.float32))
    np.testing.assert_allclose(render.depth[expected], 2.5, rtol=1e-6)
    assert np.isinf(render.depth[~expected]).all()


def test_same_image_after_moving_camera_and_objects_together() -> None:
    rng = np.random.default_rng(7)
    K = pinhole(60.0, 39.5, 29.5)
    objects = [
        VirtualObject(make_shape("sphere"), pose(translation=(0.3, 0.1, 2.5)), scale=0.8),
        VirtualObject(make_shape("cylinder"), pose(random_rotation(rng), (-0.4, -0.2, 3.0)), 0.6, (1, 0, 0)),
    ]
    G = pose(random_rotation(rng), rng.normal(size=3))
    moved = [VirtualObject(o.mesh, G @ o.T_world_obj, o.scale, o.color) for o in objects]
    a = render_objects(objects, K, pose(), 80, 60)
    b = render_objects(moved, K, G, 80, 60)
    assert (a.coverage > 0).sum() > 300
    assert np.abs(a.coverage - b.coverage).sum() <= 1.0
    both = np.isfinite(a.depth) & np.isfinite(b.depth)
    np.testing.assert_allclose(a.depth[both], b.depth[both], rtol=1e-5)
    np.testing.assert_allclose(a.rgb[both], b.rgb[both], atol=2e-3)


def test_lambert_face_turned_to_the_light_is_brighter() -> None:
    """A cube turned 45 degrees shows two faces with normals (-1, 0, -1)/sqrt2 (left) and
    (1, 0, -1)/sqrt2 (right); light travelling right (+x) lights only the left one."""
    light = Light(direction=(1.0, 0.0, 0.2), ambient=0.3, diffuse=0.7)
    albedo = np.array([0.9, 0.6, 0.3], np.float32)
    cube = VirtualObject(make_shape("cube"), pose(rot_y(45), (0, 0, 3)), scale=1.0, color=albedo)
    render = render_objects([cube], pinhole(100.0, 31.5, 23.5), pose(), 64, 48, light=light)
    to_light = -np.array([1.0, 0.0, 0.2]) / np.linalg.norm([1.0, 0.0, 0.2])
    left_lambert = max(0.0, np.array([-1, 0, -1]) @ to_light / np.sqrt(2))
    right_lambert = max(0.0, np.array([1, 0, -1]) @ to_light / np.sqrt(2))
    assert left_lambert > 0.5 and right_lambert == 0.0
    np.testing.assert_allclose(render.rgb[24, 22], albedo * (0.3 + 0.7 * left_lambert), atol=1e-5)
    np.testing.assert_allclose(render.rgb[24, 41], albedo * 0.3, atol=1e-5)


def test_world_frame_light_turns_with_the_camera() -> None:
    rng = np.random.default_rng(3)
    R = random_rotation(rng)
    camera = pose(R, (0.5, -0.2, 0.1))
    cube = VirtualObject(make_shape("cube"), camera @ pose(rot_y(30), (0, 0, 3)), scale=1.0, color=(1, 1, 1))
    K = pinhole(100.0, 31.5, 23.5)
    in_camera = render_objects([cube], K, camera, 64, 48, light=Light(direction=(1.0, 0.5, 0.5)))
    world_direction = tuple(R @ np.array([1.0, 0.5, 0.5]))
    in_world = render_objects([cube], K, camera, 64, 48, light=Light(direction=world_direction, in_camera_frame=False))
    np.testing.assert_allclose(in_world.rgb, in_camera.rgb, atol=1e-5)
    # Lit faces (above the 0.35 ambient) and at least two different shades are on screen.
    assert in_camera.rgb.max() > 0.55 and np.unique(in_camera.rgb[in_camera.coverage == 1][:, 0].round(3)).size >= 2


def test_smooth_sphere_is_brightest_where_it_faces_a_headlight() -> None:
    light = Light(direction=(0.0, 0.0, 1.0), ambient=0.2, diffuse=0.8)
    sphere = VirtualObject(make_shape("sphere"), pose(translation=(0, 0, 3)), scale=1.0, color=(1, 1, 1))
    render = render_objects([sphere], pinhole(100.0, 31.5, 23.5), pose(), 64, 48, light=light, supersample=1)
    row = render.rgb[23:25, 31:52, 0].mean(axis=0)  # centre to the right rim
    assert row[0] > 0.97
    assert (np.diff(row) < 1e-3).all(), "brightness falls off from the centre"
    assert row[-2] < 0.75


def test_antialiased_edges_have_fractional_coverage() -> None:
    """Same cube with cx = 32: its edges run through pixel centres, so 2x2 supersampling
    covers half of each edge pixel and a quarter of each corner pixel."""
    K = pinhole(100.0, 32.0, 24.0)
    cube = VirtualObject(make_shape("cube"), pose(translation=(0, 0, 3)), scale=1.0, color=(1.0, 0.0, 0.0))
    render = render_objects([cube], K, pose(), 64, 48, supersample=2)
    assert render.coverage[20, 12] == 0.5 and render.coverage[20, 52] == 0.5
    assert render.coverage[4, 30] == 0.5 and render.coverage[44, 30] == 0.5
    assert render.coverage[4, 12] == 0.25 and render.coverage[44, 52] == 0.25
    assert render.coverage[20, 30] == 1.0 and render.coverage[20, 11] == 0.0
    background = np.zeros((48, 64, 3), np.float32)
    background[..., 2] = 1.0
    result = composite(background, np.zeros((48, 64), np.float32), [cube], K, pose(), supersample=2)
    inner = result.rgb[20, 30]
    np.testing.assert_allclose(result.rgb[20, 12], 0.5 * inner + 0.5 * background[20, 12], atol=1e-6)
    # Without supersampling the same edge is all or nothing.
    aliased = render_objects([cube], K, pose(), 64, 48, supersample=1)
    assert set(np.unique(aliased.coverage)) <= {0.0, 1.0}


def test_back_face_culling_changes_nothing_in_the_image() -> None:
    torus = trimesh.creation.torus(major_radius=0.35, minor_radius=0.15, major_sections=24, minor_sections=12)
    objects = [
        VirtualObject(make_shape("cube"), pose(rot_y(30), (-0.5, 0.0, 2.5)), scale=0.6),
        VirtualObject(make_shape("sphere"), pose(translation=(0.2, 0.1, 2.2)), scale=0.5),
        VirtualObject(ObjectMesh(torus.vertices, torus.faces), pose(rot_y(60), (0.5, -0.2, 2.0))),
    ]
    assert all(o.mesh.outward_winding != 0 for o in objects)
    K = pinhole(60.0, 39.5, 29.5)
    culled = rasterize_objects(objects, K, pose(), 80, 60, cull_back_faces=True).dense()
    full = rasterize_objects(objects, K, pose(), 80, 60, cull_back_faces=False).dense()
    np.testing.assert_array_equal(np.isfinite(culled[0]), np.isfinite(full[0]))
    covered = np.isfinite(full[0])
    np.testing.assert_allclose(culled[0][covered], full[0][covered], rtol=1e-6)
    assert (np.abs(culled[1] - full[1]).max(axis=-1) > 1e-3).sum() <= 0.005 * covered.sum()


# ---------------------------------------------------------------------------------------
# Compositing.


@pytest.mark.parametrize("supersample", [1, 2, 3])
def test_composite_matches_reference_loop(supersample: int, device: str) -> None:
    rng = np.random.default_rng(10 + supersample)
    tri, rgb = random_triangles(rng, 6)
    K = pinhole(20.0, 11.5, 8.5)
    layer = rasterize_triangles(tri, rgb, K, 24, 18, supersample=supersample, device=device)
    background = rng.uniform(0, 1, (18, 24, 3)).astype(np.float32)
    scene = rng.uniform(0.3, 2.5, (18, 24)).astype(np.float32)
    scene[rng.uniform(size=scene.shape) < 0.1] = 0.0
    scene[0, :3] = [np.nan, np.inf, -1.0]
    result = composite_layer(background, scene, layer, depth_tolerance=0.05)
    sample_depth, sample_rgb = layer.dense()
    ref_rgb, ref_object, ref_occlusion = composite_reference(
        background, scene, sample_depth, sample_rgb, supersample, 0.05
    )
    assert ref_object.sum() > 20 and ref_occlusion.sum() > 20
    np.testing.assert_allclose(result.rgb, ref_rgb, atol=1e-5)
    np.testing.assert_array_equal(result.object_mask, ref_object)
    np.testing.assert_array_equal(result.occlusion_mask, ref_occlusion)
    assert not (result.object_mask & result.occlusion_mask).any()


def plane_depth(K: np.ndarray, width: int, height: int, normal: np.ndarray, offset: float) -> np.ndarray:
    """(H, W) z of the plane ``normal . X = offset`` along each pixel's ray."""
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    return (offset / (rays @ normal)).astype(np.float32)


def test_object_half_behind_a_plane_is_hidden_exactly_where_the_plane_is_nearer() -> None:
    """A sphere centred on a steep plane: the part behind it is occluded, per pixel."""
    K = pinhole(80.0, 39.5, 29.5)
    normal = np.array([1.0, 0.0, -0.5]) / np.linalg.norm([1.0, 0.0, -0.5])
    centre = np.array([0.0, 0.0, 3.0])
    scene = plane_depth(K, 80, 60, normal, normal @ centre)
    sphere = VirtualObject(make_shape("sphere"), pose(translation=centre), scale=1.2, color=(0, 1, 0))
    background = np.full((60, 80, 3), 0.5, np.float32)
    result = composite(background, scene, [sphere], K, pose(), depth_tolerance=0.01, supersample=1)
    object_depth = render_objects([sphere], K, pose(), 80, 60, supersample=1).depth
    footprint = np.isfinite(object_depth)
    nearer = object_depth < scene + 0.01
    decided = np.abs(object_depth - scene - 0.01) > 1e-4  # leave float ties at the seam out
    np.testing.assert_array_equal(result.object_mask[decided], (footprint & nearer)[decided])
    np.testing.assert_array_equal(result.occlusion_mask[decided], (footprint & ~nearer)[decided])
    assert result.object_mask.sum() > 0.15 * footprint.sum() and result.occlusion_mask.sum() > 0.15 * footprint.sum()
    np.testing.assert_array_equal(result.rgb[result.occlusion_mask], background[result.occlusion_mask])
    # Unknown scene depth (0) never hides anything.
    unknown = composite(background, np.zeros_like(scene), [sphere], K, pose(), supersample=1)
    np.testing.assert_array_equal(unknown.object_mask, footprint)
    assert not unknown.occlusion_mask.any()


def quad_mesh(size: float) -> ObjectMesh:
    """A square of side ``size`` in the object's xy plane (normal along z)."""
    h = size / 2
    return ObjectMesh(vertices=[[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], faces=[[0, 1, 2], [0, 2, 3]])


def test_occlusion_iou_against_gt_depth_composite() -> None:
    """The issue's figure on an analytic scene: a tilted wall and a real box, with exact depth
    rendered from their meshes. Virtual objects straddle the wall and hide partly behind the
    box. A degraded depth (1 cm noise, 3 % holes, as a map render would give) must give an
    occlusion mask with IoU >= 0.95 against the one from the exact depth."""
    width, height = 160, 120
    K = pinhole(130.0, 79.5, 59.5)
    real = [
        VirtualObject(quad_mesh(8.0), pose(rot_y(-25), (0.0, 0.0, 4.0)), color=(0.8, 0.8, 0.7)),
        VirtualObject(make_shape("cube"), pose(rot_y(20), (-0.45, 0.25, 2.4)), scale=0.7, color=(0.5, 0.3, 0.2)),
    ]
    gt_depth = render_objects(real, K, pose(), width, height, supersample=1).depth
    gt_depth[~np.isfinite(gt_depth)] = 0.0
    background = render_objects(real, K, pose(), width, height).rgb
    virtual = [
        VirtualObject(make_shape("sphere"), pose(translation=(-0.1, 0.15, 3.0)), scale=0.7, color=(0.1, 0.4, 0.9)),
        VirtualObject(make_shape("cylinder"), pose(rot_y(70), (0.9, -0.3, 4.6)), scale=0.8, color=(0.9, 0.2, 0.2)),
    ]
    exact = composite(background, gt_depth, virtual, K, pose())
    footprint = exact.object_mask | exact.occlusion_mask
    assert exact.occlusion_mask.sum() > 0.3 * footprint.sum(), "objects must be partly hidden"
    assert exact.object_mask.sum() > 0.3 * footprint.sum(), "objects must be partly visible"

    rng = np.random.default_rng(0)
    degraded = gt_depth + rng.normal(0.0, 0.01, gt_depth.shape).astype(np.float32)
    degraded[rng.uniform(size=gt_depth.shape) < 0.03] = 0.0
    estimated = composite(background, degraded, virtual, K, pose())
    assert mask_iou(estimated.occlusion_mask, exact.occlusion_mask) >= 0.95
    # The measure is not lenient: a depth 20 cm too far loses most of the occlusion.
    too_far = composite(background, np.where(gt_depth > 0, gt_depth + 0.2, 0.0), virtual, K, pose())
    assert mask_iou(too_far.occlusion_mask, exact.occlusion_mask) < 0.8


def test_composite_rejects_mismatched_inputs() -> None:
    cube = VirtualObject(make_shape("cube"), pose(translation=(0, 0, 3)))
    K = pinhole(50.0, 15.5, 11.5)
    with pytest.raises(ValueError, match="scene_depth"):
        composite(np.zeros((24, 32, 3)), np.zeros((24, 31)), [cube], K, pose())
    with pytest.raises(ValueError, match="background_rgb"):
        composite(np.zeros((24, 32)), np.zeros((24, 32)), [cube], K, pose())
    with pytest.raises(ValueError, match="K"):
        composite(np.zeros((24, 32, 3)), np.zeros((24, 32)), [cube], np.eye(4), pose())
    empty = composite(np.full((24, 32, 3), 0.25), np.zeros((24, 32)), [], K, pose())
    assert not empty.object_mask.any() and np.allclose(empty.rgb, 0.25)


# ---------------------------------------------------------------------------------------
# Shapes and meshes.


def test_builtin_shapes_are_unit_sized_closed_and_centred() -> None:
    for name in SHAPES:
        mesh = make_shape(name)
        assert mesh.outward_winding != 0, name
        low, high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        if name == "axes":
            np.testing.assert_allclose(high, 1.0, atol=0.03)
            assert mesh.vertex_colors is not None
        else:
            np.testing.assert_allclose(low, -0.5, atol=1e-6)
            np.testing.assert_allclose(high, 0.5, atol=1e-6)
    with pytest.raises(ValueError, match="torus"):
        make_shape("torus")


def test_mesh_and_object_validation() -> None:
    with pytest.raises(ValueError, match="faces"):
        ObjectMesh(vertices=np.zeros((3, 3)), faces=[[0, 1, 3]])
    with pytest.raises(ValueError, match="vertex_colors"):
        ObjectMesh(vertices=np.eye(3), faces=[[0, 1, 2]], vertex_colors=np.zeros((2, 3)))
    open_mesh = ObjectMesh(vertices=np.eye(3), faces=[[0, 1, 2]])
    assert open_mesh.outward_winding == 0
    box = trimesh.creation.box()
    far_box = box.vertices + [3.0, 0.0, 0.0]
    two_boxes = ObjectMesh(np.concatenate([box.vertices, far_box]), np.concatenate([box.faces, box.faces + 8]))
    assert two_boxes.outward_winding == 1
    one_inside_out = np.concatenate([box.faces, box.faces[:, ::-1] + 8])
    assert ObjectMesh(two_boxes.vertices, one_inside_out).outward_winding == 0
    with pytest.raises(ValueError, match="rotation"):
        VirtualObject(open_mesh, np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="scale"):
        VirtualObject(open_mesh, np.eye(4), scale=0.0)
    with pytest.raises(ValueError, match="color"):
        VirtualObject(open_mesh, np.eye(4), color=(1.2, 0, 0))


# ---------------------------------------------------------------------------------------
# Assets.


def export_bytes(mesh: trimesh.Trimesh | trimesh.Scene, file_type: str) -> bytes:
    data = mesh.export(file_type=file_type)
    return data.encode() if isinstance(data, str) else data


@pytest.mark.parametrize("file_type", ["glb", "obj", "ply"])
def test_asset_round_trip(file_type: str, tmp_path) -> None:
    box = trimesh.creation.box(extents=(0.2, 0.4, 0.6))
    data = export_bytes(box, file_type)
    mesh = load_asset(data, f"box.{file_type}")
    assert mesh.num_faces == 12
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [-0.1, -0.2, -0.3], atol=1e-6)
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [0.1, 0.2, 0.3], atol=1e-6)
    assert mesh.outward_winding != 0
    path = tmp_path / f"box.{file_type}"
    path.write_bytes(data)
    assert load_asset(path).num_faces == 12


def test_asset_colours_are_kept() -> None:
    box = trimesh.creation.box()
    box.visual.vertex_colors = np.tile([255, 0, 0, 255], (len(box.vertices), 1))
    mesh = load_asset(export_bytes(box, "ply"), "red.ply")
    np.testing.assert_allclose(mesh.vertex_colors, np.tile([1.0, 0.0, 0.0], (len(mesh.vertices), 1)))
    faced = trimesh.creation.box()
    faced.visual.face_colors = np.tile([0, 0, 255, 255], (12, 1))
    faced.visual.face_colors[0] = [0, 255, 0, 255]
    mesh = load_asset(export_bytes(faced, "ply"), "faces.ply")
    assert mesh.num_faces == 12
    corner_colors = mesh.vertex_colors[mesh.faces]  # (F, 3 corners, 3)
    np.testing.assert_allclose(corner_colors[0], [[0, 1, 0]] * 3)
    np.testing.assert_allclose(corner_colors[1:], np.broadcast_to([0.0, 0.0, 1.0], (11, 3, 3)))


def test_asset_texture_is_sampled_into_vertex_colours() -> None:
    image_module = pytest.importorskip("PIL.Image")
    box = trimesh.creation.box()
    uv = np.random.default_rng(0).uniform(0, 1, (len(box.vertices), 2))
    texture = image_module.fromarray(np.full((8, 8, 3), [204, 51, 0], np.uint8))
    box.visual = trimesh.visual.TextureVisuals(uv=uv, image=texture)
    mesh = load_asset(export_bytes(box, "glb"), "textured.glb")
    expected = np.broadcast_to([0.8, 0.2, 0.0], mesh.vertex_colors.shape)
    np.testing.assert_allclose(mesh.vertex_colors, expected, atol=1e-6)


def test_asset_scene_is_flattened_with_node_transforms() -> None:
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(extents=(1, 1, 1)), transform=pose(translation=(-2, 0, 0)))
    scene.add_geometry(trimesh.creation.icosphere(subdivisions=1, radius=0.5), transform=pose(translation=(2, 0, 0)))
    mesh = load_asset(export_bytes(scene, "glb"), "scene.glb")
    assert mesh.num_faces == 12 + 80
    np.testing.assert_allclose(mesh.vertices[:, 0].min(), -2.5, atol=1e-6)
    np.testing.assert_allclose(mesh.vertices[:, 0].max(), 2.5, atol=1e-6)


def test_bad_assets_raise_asset_error() -> None:
    glb = export_bytes(trimesh.creation.box(), "glb")
    cases = {
        "garbage.glb": b"this is not a mesh at all" * 10,
        "truncated.glb": glb[: len(glb) // 2],
        "empty.ply": b"",
        "garbage.ply": b"ply\nformat nonsense\n\x00\x01",
        "box.stl": export_bytes(trimesh.creation.box(), "stl"),
        "points.ply": export_bytes(trimesh.PointCloud(np.random.default_rng(0).normal(size=(20, 3))), "ply"),
        "text.obj": b"hello\nworld\n",
    }
    for name, data in cases.items():
        with pytest.raises(AssetError, match=name.split(".")[0]):
            load_asset(data, name)
    with pytest.raises(AssetError, match="too large"):
        load_asset(glb, "box.glb", max_faces=10)
    with pytest.raises(AssetError, match="filename"):
        load_asset(glb)
    assert issubclass(AssetError, ValueError)


# ---------------------------------------------------------------------------------------
# The object spec.


def test_load_objects_json_from_list_dict_and_file(tmp_path) -> None:
    asset = load_asset(export_bytes(trimesh.creation.box(), "glb"), "box.glb")
    T = pose(rot_y(30), (1.0, 2.0, 3.0))
    spec = [
        {"shape": "cube", "T_world_obj": T.tolist(), "scale": 0.25, "color": [1, 0, 0]},
        {"asset": "abc123"},
        {"shape": "axes", "scale": 2},
    ]
    objects = load_objects_json(spec, asset_resolver={"abc123": asset}.__getitem__)
    assert len(objects) == 3
    np.testing.assert_allclose(objects[0].T_world_obj, T)
    assert objects[0].scale == 0.25 and objects[0].color.tolist() == [1.0, 0.0, 0.0]
    assert objects[1].mesh is asset and objects[1].color is None
    np.testing.assert_array_equal(objects[1].T_world_obj, np.eye(4))
    path = tmp_path / "objects.json"
    path.write_text(json.dumps({"objects": spec[::2]}))
    from_file = load_objects_json(path)
    assert [o.scale for o in from_file] == [0.25, 2.0]


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"shape": "torus"}, r"objects\[1\]\.shape"),
        ({"shape": "cube", "asset": "x"}, "exactly one"),
        ({"scale": 1}, "exactly one"),
        ({"shape": "cube", "T_world_obj": [[1, 0, 0], [0, 1, 0]]}, r"objects\[1\]\.T_world_obj"),
        ({"shape": "cube", "T_world_obj": np.diag([2, 2, 2, 1.0]).tolist()}, "rotation"),
        ({"shape": "cube", "scale": -1}, "scale"),
        ({"shape": "cube", "scale": "big"}, "scale"),
        ({"shape": "cube", "color": [1, 0]}, "color"),
        ({"shape": "cube", "colour": [1, 0, 0]}, "unknown key"),
        ({"asset": "missing"}, "unknown asset id"),
        ("cube", "expected an object"),
    ],
)
def test_load_objects_json_rejects_bad_entries(entry, message: str) -> None:
    spec = [{"shape": "sphere"}, entry]
    with pytest.raises(ObjectSpecError, match=message):
        load_objects_json(spec, asset_resolver={}.__getitem__)


def test_load_objects_json_file_and_resolver_errors(tmp_path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ObjectSpecError, match="bad.json"):
        load_objects_json(bad)
    with pytest.raises(ObjectSpecError, match="no asset resolver"):
        load_objects_json([{"asset": "abc"}])
    with pytest.raises(ObjectSpecError, match="list"):
        load_objects_json({"shape": "cube"})


def test_ar_imports_no_server_code() -> None:
    """Imports point inward (server -> ar -> slam): no ar module names a server package."""
    package = Path(ar.__file__).parent
    imported = set()
    for source in package.glob("*.py"):
        for node in ast.walk(ast.parse(source.read_text())):
            if isinstance(node, ast.Import):
                imported |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                imported.add(node.module.split(".")[0])
    assert {"numpy", "torch", "trimesh", "ar"} <= imported
    assert not imported & {"server", "fastapi", "viser", "uvicorn", "starlette"}
