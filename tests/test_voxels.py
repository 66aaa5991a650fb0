"""Sparse voxel map (slam.voxels): Morton codes, allocation, shared corners, growth, persistence."""

from __future__ import annotations

import itertools

import pytest
import torch

from slam.voxels import (
    CORNER_OFFSETS,
    MORTON_BITS,
    MORTON_OFFSET,
    SparseVoxelMap,
    grow_adam_state,
    lookup_sorted,
    morton_add,
    morton_decode,
    morton_encode,
)

LOW, HIGH = -(1 << 20), (1 << 20) - 1


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def reference_code(i: int, j: int, k: int) -> int:
    """Bit-by-bit interleave in plain Python (x -> bit 3b, y -> 3b+1, z -> 3b+2), offset 2^20."""
    code = 0
    for axis, value in enumerate((i, j, k)):
        u = value + MORTON_OFFSET
        for bit in range(MORTON_BITS):
            code |= ((u >> bit) & 1) << (3 * bit + axis)
    return code


def ijk(*rows) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.int64)


def centres(coords, voxel_size: float) -> torch.Tensor:
    """(N, 3) float points at the centres of the given voxels."""
    return (torch.as_tensor(coords, dtype=torch.float64) + 0.5) * voxel_size


# ------------------------------------------------------------------ Morton
def test_golden_codes_of_small_coordinates():
    # Offset 2^20 on every axis sets bit 60, 61 and 62; (1, 2, 3) adds x bit0 -> 1,
    # y bit1 -> bit 4, z bits 0 and 1 -> bits 2 and 5.
    assert morton_encode(ijk([0, 0, 0])).tolist() == [0x7000000000000000]
    assert morton_encode(ijk([1, 2, 3])).tolist() == [0x7000000000000035]
    assert morton_encode(ijk([-1, 0, 0])).tolist() == [reference_code(-1, 0, 0)]
    assert reference_code(1, 2, 3) == 0x7000000000000035


def test_encode_matches_reference_and_round_trips_with_negatives():
    gen = torch.Generator().manual_seed(0)
    coords = torch.randint(LOW, HIGH + 1, (500, 3), generator=gen)
    coords = torch.cat([coords, ijk([LOW, LOW, LOW], [HIGH, HIGH, HIGH], [LOW, 0, HIGH],
                                    [-1, -1, -1], [0, 0, 0], [-5000, 5000, -5000])])
    codes = morton_encode(coords)
    assert codes.dtype == torch.int64
    assert bool((codes >= 0).all()), "63-bit codes must stay non-negative in int64"
    assert codes.tolist() == [reference_code(*c) for c in coords.tolist()]
    assert torch.equal(morton_decode(codes), coords)


def test_codes_sort_like_the_z_order_of_the_reference():
    coords = torch.tensor(list(itertools.product(range(-2, 2), repeat=3)))
    codes = morton_encode(coords)
    assert len(set(codes.tolist())) == len(coords), "distinct voxels need distinct codes"
    assert torch.argsort(codes).tolist() == sorted(range(len(coords)),
                                                   key=lambda n: reference_code(*coords[n].tolist()))


@pytest.mark.parametrize("bad", [[LOW - 1, 0, 0], [0, HIGH + 1, 0], [0, 0, 1 << 40]])
def test_encode_outside_the_range_raises(bad):
    with pytest.raises(ValueError, match="Morton range"):
        morton_encode(ijk([0, 0, 0], bad))


def test_encode_of_nothing_is_empty():
    assert morton_encode(torch.zeros(0, 3, dtype=torch.int64)).shape == (0,)


def test_morton_add_equals_decode_add_encode():
    gen = torch.Generator().manual_seed(1)
    coords = torch.randint(-100000, 100000, (300, 3), generator=gen)
    codes = morton_encode(coords)
    offsets = [tuple(o) for o in torch.randint(-70000, 70000, (25, 3), generator=gen).tolist()]
    offsets += [(0, 0, 0), (1, 0, 0), (0, -1, 0), (0, 0, 1), (-1, -1, -1), (1, 1, 1)]
    for offset in offsets:
        expected = morton_encode(coords + torch.tensor(offset))
        assert torch.equal(morton_add(codes, offset), expected), offset


def test_morton_add_gives_the_26_neighbours():
    codes = morton_encode(ijk([-1, 0, 7]))
    for offset in itertools.product((-1, 0, 1), repeat=3):
        got = morton_decode(morton_add(codes, offset))
        assert got.tolist() == [[-1 + offset[0], offset[1], 7 + offset[2]]]


# -------------------------------------------------------------- allocation
def test_voxels_one_kilometre_apart_in_every_direction():
    vmap = SparseVoxelMap(0.2, embed_dim=4)
    points = torch.tensor([[0.0, 0.0, 0.0],
                           [1000.0, 0.0, 0.0], [-1000.0, 0.0, 0.0],
                           [0.0, 1000.0, 0.0], [0.0, -1000.0, 0.0],
                           [0.0, 0.0, 1000.0], [0.0, 0.0, -1000.0],
                           [1000.0, -1000.0, 1000.0]]) + 0.05
    result = vmap.allocate(points)
    assert (result.new_voxels, result.observed_voxels) == (8, 8)
    assert vmap.num_voxels == 8
    assert vmap.num_corners == 8 * 8, "voxels this far apart share no corner"
    found = vmap.find_voxels(points)
    assert bool((found >= 0).all())
    assert torch.equal(vmap.voxel_coords()[found], torch.floor(points / 0.2).long())
    assert {tuple(c) for c in vmap.voxel_coords().tolist()} >= {(5000, 0, 0), (-5000, 0, 0), (0, 0, -5000), (5000, -5000, 5000)}
    assert bool((vmap.voxel_codes[1:] > vmap.voxel_codes[:-1]).all()), "codes stay sorted"


def test_two_adjacent_voxels_share_a_face_of_four_corners():
    vmap = SparseVoxelMap(0.5, embed_dim=3)
    vmap.allocate(centres([[0, 0, 0], [1, 0, 0]], 0.5))
    assert vmap.num_voxels == 2 and vmap.num_corners == 12
    a, b = vmap.find_voxels(centres([[0, 0, 0], [1, 0, 0]], 0.5)).tolist()
    rows_a, rows_b = vmap.voxel_corners[a], vmap.voxel_corners[b]
    assert len(set(rows_a.tolist()) & set(rows_b.tolist())) == 4
    # Corner c of voxel a with x bit set is corner c - 1 of voxel b.
    for c in (1, 3, 5, 7):
        assert rows_a[c] == rows_b[c - 1]


def test_a_2x2x2_block_has_27_corners_and_each_row_is_its_lattice_point():
    vmap = SparseVoxelMap(0.2, embed_dim=2)
    block = list(itertools.product((-1, 0), repeat=3))
    vmap.allocate(centres(block, 0.2))
    assert vmap.num_voxels == 8 and vmap.num_corners == 27
    assert vmap.voxel_corners.unique().numel() == 27
    # Every (voxel, corner) maps to the row stored for that lattice point's code.
    lattice = vmap.voxel_coords()[:, None, :] + CORNER_OFFSETS[None]
    rows = vmap.corner_rows[lookup_sorted(vmap.corner_codes, morton_encode(lattice.reshape(-1, 3)))]
    assert torch.equal(rows.reshape(-1, 8), vmap.voxel_corners)


def test_allocating_the_same_points_twice_adds_nothing():
    vmap = SparseVoxelMap(0.2, embed_dim=4)
    pts = torch.rand(200, 3) * 1.0
    first = vmap.allocate(pts)
    version = vmap.version
    again = vmap.allocate(pts)
    assert first.new_voxels > 0 and again.new_voxels == 0 and again.new_corners == 0
    assert again.observed_voxels == first.observed_voxels == vmap.num_voxels
    assert vmap.version == version


def test_storage_grows_by_appending_rows_only():
    vmap = SparseVoxelMap(0.2, embed_dim=5, init_std=0.01, seed=3)
    vmap.allocate(centres([[0, 0, 0], [3, 3, 3]], 0.2))
    before = vmap.embeddings.detach().clone()
    corners_before = {code: row.tolist() for code, row in zip(vmap.voxel_codes.tolist(), vmap.voxel_corners)}
    old_param = vmap.embeddings
    result = vmap.allocate(centres([[1, 0, 0], [-4, 2, 9], [0, 0, 0]], 0.2))
    assert result.new_voxels == 2 and result.observed_voxels == 3
    assert result.new_corners == 4 + 8, "the voxel next to (0,0,0) reuses its 4 face corners"
    assert vmap.embeddings is not old_param and isinstance(vmap.embeddings, torch.nn.Parameter)
    assert vmap.num_corners == before.shape[0] + result.new_corners
    assert torch.equal(vmap.embeddings.detach()[: before.shape[0]], before)
    for code, row in zip(vmap.voxel_codes.tolist(), vmap.voxel_corners):
        if code in corners_before:
            assert row.tolist() == corners_before[code], "existing voxels keep their rows"


def test_embeddings_initialised_from_a_small_normal():
    vmap = SparseVoxelMap(0.1, embed_dim=16, init_std=0.01)
    vmap.allocate(torch.rand(4000, 3) * 2.0)
    emb = vmap.embeddings.detach()
    assert emb.shape[1] == 16 and emb.dtype == torch.float32
    assert abs(float(emb.mean())) < 1e-3
    assert float(emb.std()) == pytest.approx(0.01, rel=0.05)


def test_find_voxels_and_count_new():
    vmap = SparseVoxelMap(0.2, embed_dim=2)
    vmap.allocate(centres([[0, 0, 0], [2, 0, 0]], 0.2))
    queries = torch.tensor([[0.01, 0.01, 0.01], [0.19, 0.19, 0.19], [0.45, 0.1, 0.1],
                            [0.25, 0.1, 0.1], [-0.01, 0.1, 0.1]])
    found = vmap.find_voxels(queries)
    assert (found[:3] >= 0).tolist() == [True, True, True] and found[3:].tolist() == [-1, -1]
    assert vmap.voxel_coords()[found[:3]].tolist() == [[0, 0, 0], [0, 0, 0], [2, 0, 0]]
    version, corners = vmap.version, vmap.num_corners
    assert vmap.count_new(queries) == (4, 2), "4 distinct voxels hit, 2 of them not allocated"
    assert vmap.version == version and vmap.num_voxels == 2 and vmap.num_corners == corners


def test_nbytes_counts_embeddings_and_index():
    vmap = SparseVoxelMap(0.2, embed_dim=16)
    assert vmap.nbytes() == 0
    vmap.allocate(centres(list(itertools.product((0, 1), repeat=3)), 0.2))
    nv, nc = vmap.num_voxels, vmap.num_corners
    assert (nv, nc) == (8, 27)
    assert vmap.nbytes() == nc * 16 * 4 + nv * 8 + nv * 8 * 8 + nc * 8 * 2


# ------------------------------------------------------------ optimisation
def test_grow_adam_state_keeps_old_moments_and_zeros_new_rows():
    vmap = SparseVoxelMap(0.2, embed_dim=4, seed=0)
    vmap.allocate(centres([[0, 0, 0]], 0.2))
    old = vmap.embeddings
    decoder_weight = torch.nn.Parameter(torch.ones(3))
    opt = torch.optim.Adam([{"params": [old], "lr": 0.1}, {"params": [decoder_weight], "lr": 0.1}])
    (old.square().sum() + decoder_weight.sum()).backward()
    opt.step()
    moments = {k: v.clone() for k, v in opt.state[old].items() if torch.is_tensor(v)}
    vmap.allocate(centres([[5, 5, 5]], 0.2))
    new = vmap.embeddings
    grow_adam_state(opt, old, new)
    assert opt.param_groups[0]["params"][0] is new
    assert old not in opt.state
    state = opt.state[new]
    for key in ("exp_avg", "exp_avg_sq"):
        assert state[key].shape == new.shape
        assert torch.equal(state[key][: old.shape[0]], moments[key])
        assert not bool(state[key][old.shape[0]:].any())
    assert torch.equal(torch.as_tensor(state["step"]), torch.as_tensor(moments["step"]))
    # The grown optimiser keeps working, and moves old rows and new rows alike.
    before = new.detach().clone()
    opt.zero_grad()
    new.square().sum().backward()
    opt.step()
    assert bool((new.detach() != before).any(dim=1).all())


def test_grow_adam_state_before_any_step_only_swaps_the_parameter():
    vmap = SparseVoxelMap(0.2, embed_dim=4)
    vmap.allocate(centres([[0, 0, 0]], 0.2))
    old = vmap.embeddings
    opt = torch.optim.Adam([old], lr=0.1)
    vmap.allocate(centres([[1, 1, 1]], 0.2))
    grow_adam_state(opt, old, vmap.embeddings)
    assert opt.param_groups[0]["params"][0] is vmap.embeddings and not opt.state


# ------------------------------------------------------------- persistence
def test_state_dict_round_trip():
    vmap = SparseVoxelMap(0.25, embed_dim=6, init_std=0.02, seed=4)
    vmap.allocate(torch.rand(300, 3) * 2 - 1)
    with torch.no_grad():
        vmap.embeddings.add_(1.0)  # trained values, not the initial ones, must come back
    copy = SparseVoxelMap.from_state_dict(vmap.state_dict())
    assert (copy.voxel_size, copy.embed_dim, copy.init_std, copy.version) == (0.25, 6, 0.02, vmap.version)
    for name in ("voxel_codes", "voxel_corners", "corner_codes", "corner_rows", "embeddings"):
        assert torch.equal(getattr(copy, name).detach(), getattr(vmap, name).detach()), name
    assert isinstance(copy.embeddings, torch.nn.Parameter)
    queries = torch.rand(100, 3) * 2 - 1
    assert torch.equal(copy.find_voxels(queries), vmap.find_voxels(queries))
    # The copy grows on its own without touching the original.
    copy.allocate(torch.tensor([[10.0, 10.0, 10.0]]))
    assert copy.num_voxels == vmap.num_voxels + 1
