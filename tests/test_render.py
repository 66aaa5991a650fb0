"""Volume renderer (slam.render): traversal, sampling, interpolation, weights, rendering.

Hand-worked tiny examples first, then comparisons against plain references written here: a
per-ray Amanatides-Woo DDA for the traversal and brute-force grids for the sampling.
"""

from __future__ import annotations


import numpy as np
import pytest
import torch

from slam.config import preset
from slam.decoder import Decoder
from slam.render import (
    MapView,
    RaySamples,
    Segments,
    TrainingThinning,
    VoxelHits,
    accumulate_along_rays,
    camera_rays,
    first_zero_crossing,
    interpolate_embeddings,
    interpolate_embeddings_reference,
    interpolate_with_gradient,
    ray_voxel_intersections,
    rays_in_map,
    render_rays,
    sample_points_from_hits,
    sample_points_in_band,
    sdf_weights,
    sdf_weights_and_slope,
    thin_training_samples,
    trilinear_weights,
)
from slam.voxels import CORNER_OFFSETS, SparseVoxelMap, morton_decode, morton_encode


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def sorted_codes(coords) -> torch.Tensor:
    return torch.sort(morton_encode(torch.as_tensor(coords, dtype=torch.int64))).values


def one_ray(origin, direction, near, far, coords, voxel_size=1.0, max_hits=0, dtype=torch.float64):
    codes = sorted_codes(coords)
    hits = ray_voxel_intersections(torch.tensor([origin], dtype=dtype), torch.tensor([direction], dtype=dtype),
                                   torch.tensor([near], dtype=dtype), torch.tensor([far], dtype=dtype),
                                   codes, voxel_size, max_hits)
    return codes, hits


def segments(codes, hits, ray=0):
    """[(ijk, t_in, t_out)] of one ray, in output order."""
    sel = hits.ray_index == ray
    ijk = morton_decode(codes[hits.voxel_index[sel]]).tolist()
    return [(tuple(c), float(a), float(b)) for c, a, b in zip(ijk, hits.t_in[sel], hits.t_out[sel])]


# ---------------------------------------------------------------- traversal
def test_docstring_example_two_voxels_along_z():
    codes, hits = one_ray((0.1, 0.1, -1.0), (0.0, 0.0, 1.0), 0.0, 5.0, [[0, 0, 0], [0, 0, 2]])
    assert segments(codes, hits) == [((0, 0, 0), 1.0, 2.0), ((0, 0, 2), 3.0, 4.0)]
    assert hits.ray_index.tolist() == [0, 0]


def test_negative_direction_comes_out_near_to_far():
    codes, hits = one_ray((0.1, 0.1, 5.0), (0.0, 0.0, -1.0), 0.0, 10.0, [[0, 0, 0], [0, 0, 2]])
    assert segments(codes, hits) == [((0, 0, 2), 2.0, 3.0), ((0, 0, 0), 4.0, 5.0)]


def test_ray_parallel_to_x_with_a_non_unit_direction():
    # Direction (2, 0, 0): t is in units of the direction's length, so voxels of 0.5 m take
    # 0.25 of t each. The ray starts inside voxel -2 (x = -0.9).
    coords = [[-2, 1, 3], [-1, 1, 3], [1, 1, 3], [1, 2, 3]]
    codes, hits = one_ray((-0.9, 0.7, 1.6), (2.0, 0.0, 0.0), 0.0, 10.0, coords, voxel_size=0.5)
    got = segments(codes, hits)
    expected = [((-2, 1, 3), 0.0, 0.2), ((-1, 1, 3), 0.2, 0.45), ((1, 1, 3), 0.7, 0.95)]
    assert [g[0] for g in got] == [e[0] for e in expected]
    np.testing.assert_allclose([g[1:] for g in got], [e[1:] for e in expected], atol=1e-12)


def test_diagonal_ray_through_a_corner_free_path():
    # Along (1, 1, 0) from (0.5, 0.25, 0.5): crosses x = 1 at t = 0.5, y = 1 at t = 0.75,
    # x = 2 at t = 1.5, y = 2 at t = 1.75.
    coords = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [2, 1, 0], [2, 2, 0], [0, 1, 0]]
    codes, hits = one_ray((0.5, 0.25, 0.5), (1.0, 1.0, 0.0), 0.0, 1.9, coords)
    got = segments(codes, hits)
    assert [g[0] for g in got] == [(0, 0, 0), (1, 0, 0), (1, 1, 0), (2, 1, 0), (2, 2, 0)]
    np.testing.assert_allclose([g[1:] for g in got],
                               [(0, 0.5), (0.5, 0.75), (0.75, 1.5), (1.5, 1.75), (1.75, 1.9)], atol=1e-12)


def test_max_hits_keeps_the_nearest_and_far_caps_the_last_segment():
    coords = [[0, 0, k] for k in range(6)]
    codes, hits = one_ray((0.5, 0.5, -0.5), (0.0, 0.0, 1.0), 0.0, 100.0, coords, max_hits=3)
    assert [s[0][2] for s in segments(codes, hits)] == [0, 1, 2]
    codes, hits = one_ray((0.5, 0.5, -0.5), (0.0, 0.0, 1.0), 0.0, 2.0, coords)  # far = D_max
    assert segments(codes, hits) == [((0, 0, 0), 0.5, 1.5), ((0, 0, 1), 1.5, 2.0)]
    codes, hits = one_ray((0.5, 0.5, -0.5), (0.0, 0.0, 1.0), 2.25, 3.0, coords)  # near inside a voxel
    assert segments(codes, hits) == [((0, 0, 1), 2.25, 2.5), ((0, 0, 2), 2.5, 3.0)]


def test_ray_missing_every_voxel_and_empty_map():
    codes, hits = one_ray((5.5, 5.5, -1.0), (0.0, 0.0, 1.0), 0.0, 10.0, [[0, 0, 0]])
    assert hits.ray_index.numel() == 0
    empty = torch.zeros(0, dtype=torch.int64)
    hits = ray_voxel_intersections(torch.zeros(2, 3), torch.ones(2, 3), torch.zeros(2), torch.ones(2),
                                   empty, 0.2, 8)
    assert hits.ray_index.numel() == 0 and hits.t_in.numel() == 0


def dda_reference(o, d, near, far, occupied: set, voxel_size: float):
    """Amanatides-Woo walk of one ray (float64 numpy) -> [(ijk, t_in, t_out)] of occupied voxels."""
    p = o + near * d
    cell = np.floor(p / voxel_size).astype(np.int64)
    step = np.sign(d).astype(np.int64)
    t_max = np.full(3, np.inf)
    t_delta = np.full(3, np.inf)
    for a in range(3):
        if d[a] != 0:
            boundary = (cell[a] + (1 if d[a] > 0 else 0)) * voxel_size
            t_max[a] = (boundary - o[a]) / d[a]
            t_delta[a] = voxel_size / abs(d[a])
    t = near
    out = []
    while t < far:
        a = int(np.argmin(t_max))
        t_next = min(t_max[a], far)
        if tuple(cell) in occupied and t_next > t:
            out.append((tuple(int(c) for c in cell), t, t_next))
        t = t_next
        cell[a] += step[a]
        t_max[a] += t_delta[a]
    return out


def test_traversal_matches_a_dda_reference_on_random_rays():
    rng = np.random.default_rng(7)
    voxel_size = 0.3
    grid = np.array(np.meshgrid(*[np.arange(-4, 4)] * 3, indexing="ij")).reshape(3, -1).T
    coords = grid[rng.random(len(grid)) < 0.4]
    occupied = {tuple(c) for c in coords.tolist()}
    codes = sorted_codes(coords)
    n = 150
    origins = rng.uniform(-1.2, 1.2, (n, 3))
    dirs = rng.normal(size=(n, 3)) * rng.uniform(0.5, 2.0, (n, 1))
    dirs[:10, 1:] = 0.0  # parallel to x
    dirs[10:20, :2] = 0.0  # parallel to z
    near = rng.uniform(0.0, 0.3, n)
    far = near + rng.uniform(0.5, 3.0, n)
    for max_hits in (0, 4):
        hits = ray_voxel_intersections(torch.from_numpy(origins), torch.from_numpy(dirs), torch.from_numpy(near),
                                       torch.from_numpy(far), codes, voxel_size, max_hits)
        assert bool((hits.ray_index[1:] >= hits.ray_index[:-1]).all()), "sorted by ray"
        for r in range(n):
            ref = dda_reference(origins[r], dirs[r], near[r], far[r], occupied, voxel_size)
            ref = [s for s in ref if s[2] - s[1] > 1e-6]
            if max_hits:
                ref = ref[:max_hits]
            got = [s for s in segments(codes, hits, r) if s[2] - s[1] > 1e-6]
            assert [g[0] for g in got] == [s[0] for s in ref], f"ray {r}"
            if ref:
                np.testing.assert_allclose([g[1:] for g in got], [s[1:] for s in ref], atol=1e-9)
            assert all(a[2] <= b[1] + 1e-12 for a, b in zip(got, got[1:])), "near to far"


# ----------------------------------------------------------------- sampling
def test_samples_lie_on_a_shifted_grid_inside_their_segments():
    # Ray 0: two touching segments [0.33, 1.0) and [1.0, 1.27), then [2.03, 2.1) which falls
    # between grid points (0.025 + 0.1 k); ray 1: one segment.
    hits = VoxelHits(ray_index=torch.tensor([0, 0, 0, 1]), voxel_index=torch.tensor([4, 7, 2, 1]),
                     t_in=torch.tensor([0.33, 1.0, 2.03, 0.0], dtype=torch.float64),
                     t_out=torch.tensor([1.0, 1.27, 2.1, 0.5], dtype=torch.float64))
    step = 0.1
    offsets = torch.tensor([0.25, 0.5], dtype=torch.float64)
    s = sample_points_from_hits(hits, step, offsets)
    assert bool((s.ray_index[1:] >= s.ray_index[:-1]).all())
    for h in range(4):
        r, t0, t1 = int(hits.ray_index[h]), float(hits.t_in[h]), float(hits.t_out[h])
        grid = (np.arange(-5, 40) + float(offsets[r])) * step
        expected = grid[(grid >= t0 - 1e-12) & (grid < t1 - 1e-12)]
        mine = s.t[(s.ray_index == r) & (s.voxel_index == hits.voxel_index[h])].numpy()
        np.testing.assert_allclose(mine, expected, atol=1e-12)
    ray0 = s.t[s.ray_index == 0].numpy()
    contiguous = ray0[ray0 < 1.27]
    np.testing.assert_allclose(np.diff(contiguous), step, atol=1e-12)
    assert len(s.t[s.voxel_index == 2]) == 0, "a segment between grid points holds no sample"


def test_sampling_random_segments_counts_and_bounds():
    gen = torch.Generator().manual_seed(3)
    ray = torch.sort(torch.randint(0, 20, (100,), generator=gen)).values
    t_in = torch.rand(100, generator=gen, dtype=torch.float64) * 3
    t_out = t_in + torch.rand(100, generator=gen, dtype=torch.float64)
    offsets = torch.rand(20, generator=gen, dtype=torch.float64)
    hits = VoxelHits(ray, torch.arange(100), t_in, t_out)
    s = sample_points_from_hits(hits, 0.07, offsets)
    seg = s.voxel_index  # voxel_index == segment id here
    assert bool((s.t >= t_in[seg] - 1e-12).all()) and bool((s.t < t_out[seg]).all())
    k = s.t / 0.07 - offsets[s.ray_index]
    assert torch.allclose(k, k.round(), atol=1e-9), "t = (k + offset) * step"
    counts = torch.bincount(seg, minlength=100)
    expected = torch.ceil(t_out / 0.07 - offsets[ray]) - torch.ceil(t_in / 0.07 - offsets[ray])
    assert torch.equal(counts, expected.long())
    assert torch.equal(s.ray_index, ray[seg])


# ------------------------------------------------------------ interpolation
def test_trilinear_weights_sum_to_one_and_reproduce_trilinear_functions():
    gen = torch.Generator().manual_seed(0)
    local = torch.rand(64, 3, generator=gen, dtype=torch.float64)
    w = trilinear_weights(local)
    assert w.shape == (64, 8)
    assert torch.allclose(w.sum(1), torch.ones(64, dtype=torch.float64))
    assert bool((w >= 0).all())
    coef = torch.randn(8, generator=gen, dtype=torch.float64)

    def f(p):
        x, y, z = p.unbind(-1)
        terms = torch.stack([torch.ones_like(x), x, y, z, x * y, y * z, x * z, x * y * z], -1)
        return terms @ coef

    corner_values = f(CORNER_OFFSETS.to(torch.float64))
    assert torch.allclose(w @ corner_values, f(local))
    assert torch.equal(trilinear_weights(CORNER_OFFSETS.to(torch.float64)), torch.eye(8, dtype=torch.float64))


def two_voxel_view(dtype=torch.float64, voxel_size=0.4):
    vmap = SparseVoxelMap(voxel_size, embed_dim=3, seed=5)
    vmap.allocate(torch.tensor([[0.1, 0.1, 0.1], [0.1 + voxel_size, 0.1, 0.1]]))
    emb = torch.randn(vmap.num_corners, 3, dtype=dtype, generator=torch.Generator().manual_seed(1))
    return vmap, MapView(vmap.voxel_codes, vmap.voxel_corners, emb, voxel_size)


def test_interpolation_is_continuous_across_a_shared_face():
    vmap, view = two_voxel_view()
    a, b = vmap.find_voxels(torch.tensor([[0.1, 0.1, 0.1], [0.5, 0.1, 0.1]])).tolist()
    gen = torch.Generator().manual_seed(2)
    yz = torch.rand(50, 2, generator=gen, dtype=torch.float64) * 0.4
    face = torch.cat([torch.full((50, 1), 0.4, dtype=torch.float64), yz], 1)
    from_a = interpolate_embeddings(face, torch.full((50,), a), view)
    from_b = interpolate_embeddings(face, torch.full((50,), b), view)
    assert torch.allclose(from_a, from_b, atol=1e-12)
    eps = torch.tensor([1e-7, 0.0, 0.0], dtype=torch.float64)
    near_a = interpolate_embeddings(face - eps, torch.full((50,), a), view)
    near_b = interpolate_embeddings(face + eps, torch.full((50,), b), view)
    assert torch.allclose(near_a, near_b, atol=1e-5)


def test_interpolation_at_corners_returns_the_corner_rows():
    vmap, view = two_voxel_view()
    i = 0
    ijk = view.voxel_coords[i].to(torch.float64)
    corners = (ijk[None] + CORNER_OFFSETS) * view.voxel_size
    got = interpolate_embeddings(corners, torch.full((8,), i), view)
    assert torch.allclose(got, view.embeddings[view.voxel_corners[i]], atol=1e-12)


def test_interpolation_gradcheck_wrt_embeddings_and_points():
    vmap, view = two_voxel_view()
    gen = torch.Generator().manual_seed(4)
    vidx = torch.tensor([0, 0, 1, 1, 1])
    local = 0.1 + 0.8 * torch.rand(5, 3, generator=gen, dtype=torch.float64)  # away from the clamp
    points = ((view.voxel_coords[vidx].to(torch.float64) + local) * view.voxel_size).requires_grad_(True)
    emb = view.embeddings.clone().requires_grad_(True)

    def fn(e, p):
        return interpolate_embeddings(p, vidx, MapView(view.voxel_codes, view.voxel_corners, e, view.voxel_size))

    assert torch.autograd.gradcheck(fn, (emb, points), eps=1e-6, atol=1e-6)


def test_interpolation_with_gradient_matches_autograd():
    _, view = two_voxel_view()
    gen = torch.Generator().manual_seed(5)
    vidx = torch.tensor([0, 1, 1, 0, 1, 0])
    local = 0.05 + 0.9 * torch.rand(6, 3, generator=gen, dtype=torch.float64)
    points = ((view.voxel_coords[vidx].to(torch.float64) + local) * view.voxel_size).requires_grad_(True)
    feats = interpolate_embeddings(points, vidx, view)
    fast, dfast = interpolate_with_gradient(points.detach(), vidx, view)
    assert torch.allclose(fast, feats.detach(), atol=1e-12)
    for d in range(feats.shape[1]):
        (g,) = torch.autograd.grad(feats[:, d].sum(), points, retain_graph=True)
        assert torch.allclose(dfast[:, :, d], g, atol=1e-10), d


def test_fused_interpolation_matches_the_plain_reference():
    """``interpolate_embeddings`` (embedding_bag forward, per-corner index_add backward) and
    the reference's segment gather give the per-sample reference's features, embedding
    gradients and point gradients; ``interpolate_with_gradient`` agrees too."""
    vmap = SparseVoxelMap(0.25, 4, init_std=0.5, seed=8)
    vmap.allocate(torch.rand(300, 3, generator=torch.Generator().manual_seed(9)) * 1.5)
    gen = torch.Generator().manual_seed(10)
    origins = torch.zeros(40, 3) - 0.3
    dirs = torch.rand(40, 3, generator=gen) + 0.2
    hits = ray_voxel_intersections(origins, dirs, torch.zeros(40), torch.full((40,), 3.0),
                                   vmap.voxel_codes, vmap.voxel_size, 0)
    samples = sample_points_from_hits(hits, 0.03, torch.rand(40, generator=gen))
    assert samples.segments is not None and samples.t.numel() > 2 * hits.ray_index.numel()
    assert torch.equal(samples.segments.segment_voxel[samples.segments.sample_segment], samples.voxel_index)
    r = samples.ray_index
    results = []
    fused = lambda p, v, view, segs: interpolate_embeddings(p, v, view)  # noqa: E731
    for interpolate, segs in ((interpolate_embeddings_reference, None), (interpolate_embeddings_reference, samples.segments),
                              (fused, None)):
        emb = vmap.embeddings.detach().clone().requires_grad_(True)
        pts = (origins[r] + samples.t[:, None] * dirs[r]).requires_grad_(True)
        view = MapView(vmap.voxel_codes, vmap.voxel_corners, emb, vmap.voxel_size)
        feats = interpolate(pts, samples.voxel_index, view, segs)
        (feats * torch.linspace(-1, 1, feats.numel()).reshape(feats.shape)).sum().backward()
        fast, dfast = interpolate_with_gradient(pts.detach(), samples.voxel_index, view, segs)
        results.append((feats.detach(), emb.grad, pts.grad, fast, dfast))
    assert results[0][1].abs().sum() > 0 and results[0][2].abs().sum() > 0
    for got_set in results[1:]:
        for ref, got in zip(results[0], got_set):
            assert torch.allclose(ref, got, atol=1e-6, rtol=1e-5)


def test_fused_interpolation_without_samples_or_without_point_gradients():
    _, view = two_voxel_view()
    none = interpolate_embeddings(torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, dtype=torch.long), view)
    assert none.shape == (0, 3)
    emb = view.embeddings.clone().requires_grad_(True)
    points = torch.tensor([[0.1, 0.2, 0.3], [0.5, 0.1, 0.1]], dtype=torch.float64)
    feats = interpolate_embeddings(points, torch.tensor([0, 1]),
                                   MapView(view.voxel_codes, view.voxel_corners, emb, view.voxel_size))
    feats.sum().backward()
    # Every sample's trilinear weights sum to one, so each sample hands out exactly D units.
    assert torch.isclose(emb.grad.sum(), torch.tensor(2.0 * 3, dtype=torch.float64))


# ----------------------------------------------------------------- weights
def test_sdf_weights_slope_is_the_derivative_with_the_mask_held():
    tr = 0.1
    t = torch.linspace(0.1, 1.0, 10, dtype=torch.float64)
    sdf = torch.tensor([0.9, 0.6, 0.3, 0.1, -0.1, -0.3, -0.5, 0.2, 0.4, 0.6], dtype=torch.float64)
    ray = torch.zeros(10, dtype=torch.int64)
    s = sdf.clone().requires_grad_(True)
    w_ref = sdf_weights(s, t, ray, 1, tr)
    (g,) = torch.autograd.grad(w_ref.sum(), s)
    w, slope = sdf_weights_and_slope(sdf, t, ray, 1, tr)
    assert torch.allclose(w, w_ref.detach()) and torch.allclose(slope, g)


def test_sdf_weights_formula_and_mask_around_the_first_surface():
    tr = 0.27
    t = torch.arange(1, 11, dtype=torch.float64) * 0.1  # 0.1 .. 1.0
    sdf = torch.tensor([0.9, 0.6, 0.3, 0.1, -0.1, -0.3, -0.5, 0.2, 0.4, 0.6], dtype=torch.float64)
    ray = torch.zeros(10, dtype=torch.int64)
    w = sdf_weights(sdf, t, ray, 1, tr)
    formula = torch.sigmoid(sdf / tr) * torch.sigmoid(-sdf / tr)
    # The sign changes between t = 0.4 and 0.5, at t = 0.45 by linear interpolation: samples
    # within tr of it count (0.2 .. 0.7); those in front (0.1) and behind (0.8 .. 1.0, where
    # a second surface lies) are masked.
    crossing = 0.45
    keep = (t < crossing + tr) & (t > crossing - tr)
    assert torch.allclose(w[keep], formula[keep])
    assert keep.tolist() == [False] + [True] * 6 + [False] * 3
    assert not bool(w[~keep].any())


def test_first_zero_crossing_is_interpolated_per_ray():
    # Ray 0 crosses twice (the first counts), ray 1 never, ray 2 on its last pair; the sign
    # change between ray 1's last sample and ray 2's first is none; ray 3 has no samples.
    sdf = torch.tensor([0.5, -0.5, 0.5, -0.5, 1.0, 0.8, -0.9, 0.6, -0.2])
    t = torch.tensor([1.0, 1.2, 1.4, 1.6, 1.0, 1.1, 2.0, 2.2, 2.4])
    ray = torch.tensor([0, 0, 0, 0, 1, 1, 2, 2, 2])
    got = first_zero_crossing(sdf, t, ray, 4)
    assert got[0].item() == pytest.approx(1.1)
    assert got[2].item() == pytest.approx(2.0 + 0.2 * 0.9 / 1.5)
    assert torch.isinf(got[1]) and torch.isinf(got[3])


def test_without_mask_in_front_samples_in_front_of_the_surface_keep_their_weight():
    # render.mask_in_front = False (issue 21 item 4, the paper): only samples more than tr
    # behind the first crossing are masked; the default also masks those more than tr in front.
    tr = 0.27
    t = torch.arange(1, 11, dtype=torch.float64) * 0.1
    sdf = torch.tensor([0.9, 0.6, 0.3, 0.1, -0.1, -0.3, -0.5, 0.2, 0.4, 0.6], dtype=torch.float64)
    ray = torch.zeros(10, dtype=torch.int64)
    formula = torch.sigmoid(sdf / tr) * torch.sigmoid(-sdf / tr)
    ours = sdf_weights(sdf, t, ray, 1, tr)
    paper = sdf_weights(sdf, t, ray, 1, tr, mask_in_front=False)
    keep = t < 0.45 + tr  # the crossing is at 0.45
    assert keep.tolist() == [True] * 7 + [False] * 3
    assert torch.allclose(paper[keep], formula[keep]) and not bool(paper[~keep].any())
    assert float(ours[0]) == 0.0 < float(paper[0]), "the sample at 0.1, 0.35 in front, counts only without the mask"
    assert torch.equal(ours[1:], paper[1:])
    # The Gauss-Newton tracker's closed-form weights follow the same switch.
    s = sdf.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(sdf_weights(s, t, ray, 1, tr, mask_in_front=False).sum(), s)
    w, slope = sdf_weights_and_slope(sdf, t, ray, 1, tr, mask_in_front=False)
    assert torch.allclose(w, paper) and torch.allclose(slope, g) and float(slope[0]) != 0.0


def test_sdf_weights_rays_are_independent_and_no_surface_keeps_everything():
    tr = 0.1
    t = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.1, 0.2, 0.3, 0.4, 0.5])
    sdf = torch.tensor([0.5, 0.4, 0.3, 0.2, 0.5, -0.5, -0.5, -0.5, -0.5])
    ray = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1, 1])
    w = sdf_weights(sdf, t, ray, 3, tr)
    formula = torch.sigmoid(sdf / tr) * torch.sigmoid(-sdf / tr)
    assert torch.allclose(w[:4], formula[:4]), "ray 0 has no sign change: nothing is masked"
    # Ray 1 changes sign between 0.1 and 0.2: 0.1 + 0.1 bounds it (0.2 is borderline float).
    assert torch.allclose(w[4:5], formula[4:5]) and not bool(w[6:].any())
    # The sign change 0.4 (ray 0, last) -> 0.5 (ray 1, first) crosses rays and must be ignored.
    sdf2 = torch.tensor([0.5, 0.4, 0.3, 0.2, -0.5, -0.5, -0.5, -0.5, -0.5])
    w2 = sdf_weights(sdf2, t, ray, 3, tr)
    assert torch.allclose(w2[:4], formula[:4])


def test_accumulate_along_rays():
    w = torch.tensor([1.0, 2.0, 3.0])
    v = torch.tensor([[1.0, 0.0], [0.5, 1.0], [2.0, 2.0]])
    out = accumulate_along_rays(w, v, torch.tensor([0, 0, 2]), 3)
    assert out.tolist() == [[2.0, 2.0], [0.0, 0.0], [6.0, 6.0]]


# ---------------------------------------------------------------- rendering
def test_camera_rays_and_rays_in_map():
    K = torch.tensor([[100.0, 0, 40], [0, 50.0, 30], [0, 0, 1]])
    dirs = camera_rays(K, torch.tensor([[40.0, 30.0], [140.0, 80.0]]))
    assert dirs.tolist() == [[0.0, 0.0, 1.0], [1.0, 1.0, 1.0]]
    T = torch.eye(4)
    T[:3, :3] = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90 deg about z
    T[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    o, d = rays_in_map(T, dirs)
    assert o.tolist() == [[1.0, 2.0, 3.0]] * 2
    assert torch.allclose(d, torch.tensor([[0.0, 0, 1], [-1.0, 1, 1]]))


class PlaneSDF(torch.nn.Module):
    """A decoder whose SDF (units of tr) is ``(z_plane - x0) / tr`` with x0 the first embedding
    channel, and whose colour is the next three channels; ``scale`` makes it differentiable."""

    def __init__(self, z_plane: float, truncation: float):
        super().__init__()
        self.z_plane, self.truncation = z_plane, truncation
        self.scale = torch.nn.Parameter(torch.tensor(1.0, dtype=torch.float64))

    def sdf_and_hidden(self, emb):
        return self.scale * (self.z_plane - emb[:, 0]) / self.truncation, emb

    def feature_from_hidden(self, hidden):
        return hidden[:, 1:4]

    def color(self, feature):
        return feature.clamp(0, 1)


def slab_view(voxel_size=0.2):
    """Voxels x, y in [-2, 2), z in [0, 10) with corner embeddings (z, 0.2, 0.5, 0.8)."""
    r = torch.arange(-2, 2)
    grid = torch.stack(torch.meshgrid(r, r, torch.arange(0, 10), indexing="ij"), -1).reshape(-1, 3)
    vmap = SparseVoxelMap(voxel_size, embed_dim=4)
    vmap.allocate((grid.to(torch.float64) + 0.5) * voxel_size)
    corner_z = morton_decode(vmap.corner_codes)[:, 2].to(torch.float64) * voxel_size
    emb = torch.zeros(vmap.num_corners, 4, dtype=torch.float64)
    emb[vmap.corner_rows, 0] = corner_z
    emb[:, 1:] = torch.tensor([0.2, 0.5, 0.8], dtype=torch.float64)
    return MapView(vmap.voxel_codes, vmap.voxel_corners, emb, voxel_size)


@pytest.mark.parametrize("z_plane", [0.83, 1.234, 1.5])
def test_render_depth_of_a_known_plane_is_its_zero_crossing(z_plane):
    view = slab_view()
    tr, step = 0.1, 0.02
    decoder = PlaneSDF(z_plane, tr)
    gen = torch.Generator().manual_seed(0)
    n = 32
    origins = torch.cat([torch.rand(n, 2, generator=gen, dtype=torch.float64) * 0.4 - 0.2,
                         torch.full((n, 1), 0.05, dtype=torch.float64)], 1)
    dirs = torch.cat([torch.rand(n, 2, generator=gen, dtype=torch.float64) * 0.2 - 0.1,
                      torch.ones(n, 1, dtype=torch.float64)], 1)
    out = render_rays(origins, dirs, view, decoder, near=torch.full((n,), 0.0, dtype=torch.float64),
                      far=torch.full((n,), 3.0, dtype=torch.float64), step=step, truncation=tr, max_hits=40)
    expected_t = (z_plane - origins[:, 2]) / dirs[:, 2]
    assert bool(out.hit.all())
    assert float((out.depth.detach() - expected_t).abs().max()) < step
    rgb = torch.tensor([[0.2, 0.5, 0.8]], dtype=torch.float64).expand(n, 3)
    # Colour skips samples of weight < 1e-5, so it is exact only to about that share.
    assert torch.allclose(out.color, rgb, atol=1e-3)
    exact = render_rays(origins, dirs, view, decoder, near=torch.full((n,), 0.0, dtype=torch.float64),
                        far=torch.full((n,), 3.0, dtype=torch.float64), step=step, truncation=tr, max_hits=40,
                        color_weight_eps=0.0)
    assert torch.allclose(exact.color, rgb, atol=1e-6)
    assert torch.equal(exact.depth, out.depth)
    assert bool((out.weight_sum > 0).all()) and bool((out.depth_var >= 0).all())
    # Samples live only inside the voxels they name (closed boxes: a sample may sit on a face).
    pts = origins[out.samples.ray_index] + out.samples.t[:, None] * dirs[out.samples.ray_index]
    local = pts / view.voxel_size - view.voxel_coords[out.samples.voxel_index].to(torch.float64)
    assert bool((local > -1e-9).all()) and bool((local < 1 + 1e-9).all())


def test_render_caps_samples_at_far_and_misses_report_no_hit():
    view = slab_view()
    decoder = PlaneSDF(5.0, 0.1)  # surface beyond D_max
    origins = torch.tensor([[0.0, 0.0, 0.05], [10.0, 10.0, 0.05]], dtype=torch.float64)
    dirs = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    out = render_rays(origins, dirs, view, decoder, near=torch.zeros(2, dtype=torch.float64),
                      far=torch.full((2,), 1.0, dtype=torch.float64), step=0.02, truncation=0.1, max_hits=40)
    assert out.hit.tolist() == [True, False]
    assert float(out.samples.t.max()) < 1.0
    assert out.depth[1] == 0 and out.weight_sum[1] == 0 and not bool(out.color[1].any())


def test_thinning_keeps_the_band_every_kth_free_sample_and_nothing_behind():
    # tr = 0.1. Ray 0: depth 1.0, free space t < 0.9 (0.1 ... 0.8: 8 samples), band 0.9-1.1,
    # behind > 1.1. Ray 1: invalid depth, keeps all. Ray 2: depth 0.55, phase 1.
    t0 = torch.arange(1, 14, dtype=torch.float64) / 10  # 0.1 ... 1.3
    t1 = torch.tensor([0.2, 0.4], dtype=torch.float64)
    t2 = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], dtype=torch.float64)
    t = torch.cat([t0, t1, t2])
    ray = torch.tensor([0] * 13 + [1] * 2 + [2] * 6)
    segment = torch.arange(t.numel()) // 2  # a made-up segment per pair of samples
    segment_voxel = torch.arange(int(segment.max()) + 1) * 7
    samples = RaySamples(ray, t, segment_voxel[segment], Segments(segment, segment_voxel))
    depth = torch.tensor([1.0, 0.0, 0.55], dtype=torch.float64)
    thinned = thin_training_samples(samples, TrainingThinning(depth, 0.1, 10.0, 3, torch.tensor([0, 2, 1])))
    kept = list(zip(thinned.ray_index.tolist(), [round(v, 6) for v in thinned.t.tolist()]))
    # Ray 0, phase 0: free ranks 0, 3, 6 (t 0.1, 0.4, 0.7) stand for 3; the band 0.9-1.1 stays
    # (1.1 sits on its edge); 1.2 and 1.3 go. Ray 2, phase 1: free ranks 2 (t 0.3), band 0.5, 0.6.
    assert kept == [(0, 0.1), (0, 0.4), (0, 0.7), (0, 0.9), (0, 1.0), (0, 1.1), (1, 0.2), (1, 0.4),
                    (2, 0.3), (2, 0.5), (2, 0.6)]
    assert thinned.stands_for.tolist() == [3.0, 3.0, 3.0, 1.0, 1.0, 1.0, 1.0, 1.0, 3.0, 1.0, 1.0]
    assert thinned.grid_counts.tolist() == [13, 2, 6]
    assert torch.equal(thinned.segments.segment_voxel[thinned.segments.sample_segment], thinned.voxel_index)
    # Over the stride's phases every free-space sample is kept exactly once.
    seen = torch.zeros(t.numel())
    for phase in range(3):
        th = thin_training_samples(samples, TrainingThinning(depth, 0.1, 10.0, 3, torch.full((3,), phase)))
        index = {(r, round(v, 6)): i for i, (r, v) in enumerate(zip(ray.tolist(), t.tolist()))}
        for r, v in zip(th.ray_index.tolist(), th.t.tolist()):
            seen[index[(r, round(v, 6))]] += 1
    free = torch.tensor([v < 0.9 for v in t0.tolist()] + [False] * 2 + [v < 0.45 for v in t2.tolist()])
    assert seen[free].tolist() == [1.0] * int(free.sum())


@pytest.mark.parametrize("z_plane", [0.83, 1.234])
def test_thinned_render_of_a_plane_at_the_observed_depth_is_the_full_render(z_plane):
    """Where the map's surface is at the observed depth, the samples thinning drops lie outside
    the first surface's window, so depth and colour do not change."""
    view = slab_view()
    tr, step, n = 0.1, 0.02, 32
    decoder = PlaneSDF(z_plane, tr)
    gen = torch.Generator().manual_seed(1)
    origins = torch.cat([torch.rand(n, 2, generator=gen, dtype=torch.float64) * 0.4 - 0.2,
                         torch.full((n, 1), 0.05, dtype=torch.float64)], 1)
    dirs = torch.cat([torch.rand(n, 2, generator=gen, dtype=torch.float64) * 0.2 - 0.1,
                      torch.ones(n, 1, dtype=torch.float64)], 1)
    observed = (z_plane - origins[:, 2]) / dirs[:, 2]
    kw = dict(near=torch.zeros(n, dtype=torch.float64), far=observed + 2 * tr, step=step, truncation=tr,
              max_hits=40, offsets=torch.rand(n, generator=gen, dtype=torch.float64))
    full = render_rays(origins, dirs, view, decoder, **kw)
    thinning = TrainingThinning(observed, tr, 10.0, 2, torch.randint(2, (n,), generator=gen))
    thinned = render_rays(origins, dirs, view, decoder, thinning=thinning, **kw)
    assert thinned.samples.t.numel() < 0.8 * full.samples.t.numel()
    assert torch.allclose(thinned.depth, full.depth, atol=1e-12)
    assert torch.allclose(thinned.color, full.color, atol=1e-12)
    assert torch.equal(thinned.hit, full.hit)


def random_field_and_rays(n: int):
    """A map of random voxels in front of the origin, the test preset's decoder and n rays
    into it: (SparseVoxelMap, Decoder, origins (n, 3), dirs (n, 3))."""
    torch.manual_seed(0)
    cfg = preset("test")
    vmap = SparseVoxelMap(0.2, embed_dim=cfg.voxel.embed_dim, init_std=0.3, seed=0)
    vmap.allocate(torch.rand(2000, 3) * torch.tensor([1.0, 1.0, 0.6]) + torch.tensor([-0.5, -0.5, 0.6]))
    decoder = Decoder(cfg.decoder, cfg.voxel.embed_dim)
    dirs = torch.cat([torch.rand(n, 2) * 0.4 - 0.2, torch.ones(n, 1)], 1)
    return vmap, decoder, torch.zeros(n, 3), dirs


def test_renormalised_colour_is_the_weighted_mean_over_the_coloured_samples():
    """``renormalise_color`` (views): with every sample coloured it changes nothing; with a
    high threshold the colour is the mean over the kept samples, not darkened by the others."""
    vmap, decoder, origins, dirs = random_field_and_rays(32)
    n = 32
    kw = dict(near=torch.full((n,), 0.05), far=torch.full((n,), 2.0), step=0.04, truncation=0.1, max_hits=8)
    with torch.no_grad():
        plain = render_rays(origins, dirs, MapView.of(vmap), decoder, color_weight_eps=0.0, **kw)
        same = render_rays(origins, dirs, MapView.of(vmap), decoder, color_weight_eps=0.0, renormalise_color=True, **kw)
        assert torch.allclose(plain.color, same.color, atol=1e-5)
        eps = 0.1
        high = render_rays(origins, dirs, MapView.of(vmap), decoder, color_weight_eps=eps, renormalise_color=True, **kw)
        samples = plain.samples
        points = origins[samples.ray_index] + samples.t[:, None] * dirs[samples.ray_index]
        from slam.render import color_of_hidden, decode_samples, sdf_weights
        sdf, hidden = decode_samples(points, samples.voxel_index, MapView.of(vmap), decoder)
        w = sdf_weights(sdf, samples.t, samples.ray_index, n, 0.1)
        kept = w > eps
        rgb = color_of_hidden(decoder, hidden)
        for ray in range(n):
            mine = kept & (samples.ray_index == ray)
            if bool(mine.any()):
                expected = (w[mine, None] * rgb[mine]).sum(0) / w[mine].sum()
                assert torch.allclose(high.color[ray], expected, atol=1e-5), ray
            else:
                assert not bool(high.color[ray].any())
    assert bool((kept.sum() > 0)) and bool((~kept & (w > 0)).any()), "the threshold keeps some samples, drops others"


def test_gradients_reach_embeddings_decoder_and_ray_geometry():
    vmap, decoder, origins, dirs = random_field_and_rays(16)
    n = 16
    origins, dirs = origins.requires_grad_(True), dirs.requires_grad_(True)
    out = render_rays(origins, dirs, MapView.of(vmap), decoder, near=torch.full((n,), 0.05),
                      far=torch.full((n,), 2.0), step=0.04, truncation=0.1, max_hits=8,
                      color_weight_eps=0.0)
    assert bool(out.hit.all())
    (out.depth.sum() + out.color.sum()).backward()
    for name, grad in [("embeddings", vmap.embeddings.grad), ("origins", origins.grad), ("dirs", dirs.grad)]:
        assert grad is not None and bool(torch.isfinite(grad).all()) and float(grad.abs().sum()) > 0, name
    for name, p in decoder.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), name
    assert float(decoder.sdf_head.weight.grad.abs().sum()) > 0
    assert float(decoder.color_head[-1].weight.grad.abs().sum()) > 0



def test_band_samples_are_the_traversal_samples_on_random_rays():
    """Lookup along the t grid gives the samples of traversal plus sampling (offset 0.5), for
    ranges through occupied, empty and partly occupied space."""
    view = slab_view()
    gen = torch.Generator().manual_seed(3)
    n = 64
    origins = torch.cat([torch.rand(n, 2, generator=gen, dtype=torch.float64) * 1.2 - 0.6,
                         torch.rand(n, 1, generator=gen, dtype=torch.float64) * 0.5 - 0.3], 1)
    dirs = torch.cat([torch.rand(n, 2, generator=gen, dtype=torch.float64) * 1.0 - 0.5,
                      torch.ones(n, 1, dtype=torch.float64)], 1)
    near = torch.rand(n, generator=gen, dtype=torch.float64) * 1.5
    far = near + torch.rand(n, generator=gen, dtype=torch.float64) * 0.4
    step = 0.02
    hits = ray_voxel_intersections(origins, dirs, near, far, view.voxel_codes, view.voxel_size, 0)
    traversed = sample_points_from_hits(hits, step, torch.full((n,), 0.5, dtype=torch.float64))
    looked_up = sample_points_in_band(origins, dirs, near, far, step, view)
    assert traversed.t.numel() > 100 and torch.equal(looked_up.ray_index, traversed.ray_index)
    assert torch.allclose(looked_up.t, traversed.t) and torch.equal(looked_up.voxel_index, traversed.voxel_index)
    assert sample_points_in_band(origins, dirs, far, near, step, view).t.numel() == 0
