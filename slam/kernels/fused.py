"""The field's hot path with numba's fused kernels, as torch autograd Functions.

``FusedField``: interpolation of the corner embeddings, the decoder's trunk and its SDF row
in one Function, the same numbers as
``decoder.sdf_and_hidden(slam.render.interpolate_embeddings(points, voxel_index, view))``.
The per-sample work that torch spreads over a dozen operators, each writing an (S, 8),
(S, 8, D) or (S, H) intermediate (gathers, weights, products, ReLU masks, index_add), is
one numba pass forward (gather + trilinear) and, backward, one pass for the SDF row with
the last ReLU, one per other ReLU, and one that scatters straight into the embedding rows
and the points. Every layer stays a matrix product: MKL's beat numba loops there.

``interpolate_with_slopes``: ``slam.render.interpolate_with_gradient`` in one pass.

Only for float32 CPU tensors; ``slam.kernels.use_numba`` decides.
"""

from __future__ import annotations

import numpy as np
import torch

from .backend import numba_kernels, sync_numba_threads


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class FusedField(torch.autograd.Function):
    """(points (S, 3), voxel_index (S,), coords (Nv, 3) float32, corners (Nv, 8) int64,
    voxel_size, embeddings (Nc, D), sdf_weight (1 + F, H), sdf_bias (1 + F,),
    W1, b1, ..., WL, bL the trunk's layers) -> sdf (S,), hidden (S, H).

    Differentiable in points, embeddings and every decoder parameter (the SDF head's rows
    other than the first get zero from here; ``feature_from_hidden`` adds theirs).
    Saved for backward: the interpolated x (S, D) and each layer's output (S, H), which
    plain autograd keeps too; none of its (S, 8) weights, gathered rows or masks.
    """

    @staticmethod
    def forward(ctx, points, voxel_index, coords, corners, voxel_size, embeddings, sdf_weight, sdf_bias, *layers):
        chunks = sync_numba_threads()
        S, D = points.shape[0], embeddings.shape[1]
        x = points.new_empty(S, D)
        numba_kernels().interpolate(_np(points), _np(voxel_index), _np(coords), _np(corners), _np(embeddings),
                                    np.float32(voxel_size), chunks, x.numpy())
        hs, h = [], x
        for W, b in zip(layers[0::2], layers[1::2]):
            h = torch.addmm(b.detach(), h, W.detach().t()).relu_()
            hs.append(h)
        sdf = torch.mv(h, sdf_weight.detach()[0]) + sdf_bias.detach()[0]
        ctx.save_for_backward(points, voxel_index, coords, corners, embeddings, sdf_weight, x, *hs, *layers)
        ctx.voxel_size = voxel_size
        ctx.num_layers = len(layers) // 2
        return sdf, h

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_sdf, g_hidden):
        kernels = numba_kernels()
        chunks = sync_numba_threads()
        L = ctx.num_layers
        points, voxel_index, coords, corners, embeddings, sdf_weight, x, *rest = ctx.saved_tensors
        hs, layers = [h.detach() for h in rest[:L]], rest[L:]
        need = ctx.needs_input_grad
        S = x.shape[0]
        g_sdf = hs[-1].new_zeros(S) if g_sdf is None else g_sdf.contiguous()
        g_hid = _np(g_hidden) if g_hidden is not None else np.zeros((0, 0), np.float32)
        # The SDF row and the hidden output share the last ReLU: one pass gives the
        # gradient at its input.
        g_z = torch.empty_like(hs[-1])
        kernels.head_backward(g_sdf.numpy(), g_hid, hs[-1].numpy(), _np(sdf_weight[0]), chunks, g_z.numpy())
        g_sdf_weight = g_sdf_bias = None
        if need[6]:
            g_sdf_weight = torch.zeros_like(sdf_weight)
            g_sdf_weight[0] = torch.mv(hs[-1].t(), g_sdf)
        if need[7]:
            g_sdf_bias = torch.zeros(sdf_weight.shape[0], dtype=g_sdf.dtype)
            g_sdf_bias[0] = g_sdf.sum()
        g_layers: list[torch.Tensor | None] = [None] * (2 * L)
        inputs = [x] + hs[:-1]
        for k in range(L - 1, -1, -1):
            if need[8 + 2 * k]:
                g_layers[2 * k] = g_z.t() @ inputs[k]
            if need[9 + 2 * k]:
                g_layers[2 * k + 1] = g_z.sum(0)
            if k == 0 and not (need[0] or need[5]):
                break
            g_z = g_z @ layers[2 * k].detach()
            if k > 0:
                kernels.relu_backward_(g_z.numpy(), hs[k - 1].numpy(), chunks)
        g_emb = g_points = None
        if need[0] or need[5]:
            D = embeddings.shape[1]
            g_parts = embeddings.new_zeros((chunks, embeddings.shape[0], D) if need[5] else (0, 0, D))
            g_points = points.new_empty(S, 3) if need[0] else points.new_empty(0, 3)
            kernels.interpolate_backward(
                g_z.numpy(), _np(points), _np(voxel_index), _np(coords), _np(corners), _np(embeddings),
                np.float32(ctx.voxel_size), chunks, need[5], need[0], g_parts.numpy(), g_points.numpy())
            g_emb = (g_parts[0] if chunks == 1 else g_parts.sum(0)) if need[5] else None
            g_points = g_points if need[0] else None
        return (g_points, None, None, None, None, g_emb, g_sdf_weight, g_sdf_bias, *g_layers)


def field_sdf_and_hidden(points: torch.Tensor, voxel_index: torch.Tensor, voxel_coords: torch.Tensor,
                         voxel_corners: torch.Tensor, voxel_size: float, embeddings: torch.Tensor,
                         decoder) -> tuple[torch.Tensor, torch.Tensor]:
    """``FusedField`` for a ``slam.decoder.Decoder``: points (S, 3), voxel_index (S,) ->
    sdf (S,), hidden (S, H)."""
    params = [p for layer in decoder.trunk_linears() for p in (layer.weight, layer.bias)]
    return FusedField.apply(points, voxel_index, voxel_coords, voxel_corners, voxel_size, embeddings,
                            decoder.sdf_head.weight, decoder.sdf_head.bias, *params)


def interpolate_with_slopes(points: torch.Tensor, voxel_index: torch.Tensor, voxel_coords: torch.Tensor,
                            voxel_corners: torch.Tensor, voxel_size: float,
                            embeddings: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Features (S, D) and d features / d point (S, 3, D) per metre, no autograd."""
    S, D = points.shape[0], embeddings.shape[1]
    feats = points.new_empty(S, D)
    dfeats = points.new_empty(S, 3, D)
    numba_kernels().interpolate_with_slopes(
        _np(points), _np(voxel_index), _np(voxel_coords), _np(voxel_corners), _np(embeddings),
        np.float32(voxel_size), sync_numba_threads(), feats.numpy(), dfeats.numpy())
    return feats, dfeats


def interpolate(points: torch.Tensor, voxel_index: torch.Tensor, voxel_coords: torch.Tensor,
                voxel_corners: torch.Tensor, voxel_size: float, embeddings: torch.Tensor) -> torch.Tensor:
    """Trilinear interpolation of the corner embeddings (S, D), forward only (views)."""
    x = points.new_empty(points.shape[0], embeddings.shape[1])
    numba_kernels().interpolate(_np(points), _np(voxel_index), _np(voxel_coords), _np(voxel_corners),
                                _np(embeddings), np.float32(voxel_size), sync_numba_threads(), x.numpy())
    return x


def band_samples(origins: torch.Tensor, dirs: torch.Tensor, k0: torch.Tensor, counts: torch.Tensor,
                 step: float, offset: float, voxel_size: float,
                 voxel_codes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every grid sample of every ray and its voxel (``numba_cpu.band_samples``), misses
    dropped: ray (S,) int64, t (S,) float32, voxel (S,) int64, sorted by ray, then t."""
    first = torch.cumsum(counts, 0) - counts
    total = int(counts.sum())
    ray = torch.empty(total, dtype=torch.int64)
    t = origins.new_empty(total)
    voxel = torch.empty(total, dtype=torch.int64)
    numba_kernels().band_samples(_np(origins), _np(dirs), _np(k0), _np(counts), _np(first), float(step),
                                 float(offset), np.float32(voxel_size), _np(voxel_codes), sync_numba_threads(),
                                 ray.numpy(), t.numpy(), voxel.numpy())
    keep = torch.nonzero(voxel >= 0, as_tuple=True)[0]
    return ray[keep], t[keep], voxel[keep]


def traverse(origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
             k_lo: torch.Tensor, axis_counts: torch.Tensor, voxel_codes: torch.Tensor, voxel_size: float,
             max_hits: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every ray's voxel hits (``numba_cpu.traverse``): ray (H,) int64, voxel (H,) int64,
    t_in, t_out (H,) float32, sorted by ray, then t. near, far (R,) already clipped to the
    map's box; k_lo (R, 3) float32, axis_counts (R, 3) int64: the first plane crossed per
    axis and how many."""
    intervals = axis_counts.sum(1) + 1
    capacity = intervals.clamp(max=max_hits) if max_hits > 0 else intervals
    first = torch.cumsum(capacity, 0) - capacity
    total = int(capacity.sum())
    ray = torch.full((total,), -1, dtype=torch.int64)
    voxel = torch.empty(total, dtype=torch.int64)
    t_in, t_out = origins.new_empty(total), origins.new_empty(total)
    max_bounds = int(intervals.max()) + 1 if intervals.numel() else 1
    numba_kernels().traverse(_np(origins), _np(dirs), _np(near), _np(far), _np(k_lo), _np(axis_counts), _np(first),
                             np.float32(voxel_size), _np(voxel_codes), int(max_hits), max_bounds, sync_numba_threads(),
                             ray.numpy(), voxel.numpy(), t_in.numpy(), t_out.numpy())
    keep = torch.nonzero(ray >= 0, as_tuple=True)[0]
    return ray[keep], voxel[keep], t_in[keep], t_out[keep]


def thin_mask(ray_index: torch.Tensor, t: torch.Tensor, depth: torch.Tensor, phase: torch.Tensor,
              truncation: float, max_depth: float, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Which samples ``slam.render.thin_training_samples`` keeps, (S,) bool, and what each
    stands for, (S,) float32 (``numba_cpu.thin_mask``)."""
    keep = torch.empty(t.shape[0], dtype=torch.bool)
    stands_for = t.new_empty(t.shape[0])
    numba_kernels().thin_mask(_np(ray_index), _np(t), _np(depth), _np(phase), np.float32(truncation),
                              np.float32(max_depth), int(stride), keep.numpy(), stands_for.numpy())
    return keep, stands_for


def hash_grid(points: torch.Tensor, cells: torch.Tensor, tables: torch.Tensor, rows: torch.Tensor,
              primes: tuple[int, int, int]) -> torch.Tensor:
    """The fine colour level's features (N, L * F) of (N, 3) points, (L,) float64 cell edges,
    the flat (R, F) tables, (L,) int64 rows of each level's table and the hash's 3 primes,
    forward only (views and meshes; ``slam.fine_color.hash_features``)."""
    rows = rows.to(torch.int64)
    out = points.new_empty(points.shape[0], cells.numel() * tables.shape[1])
    numba_kernels().hash_grid(_np(points), _np(cells.to(torch.float64)), _np(tables), _np(rows),
                              _np(torch.cumsum(rows, 0) - rows), np.array(primes, np.int64),
                              sync_numba_threads(), out.numpy())
    return out


def warm_up_kernels() -> None:
    """Run every kernel once on a two-voxel map (compiles, or loads numba's disk cache), in
    its serial copy and, where torch has more than one thread, its parallel one."""
    threads = torch.get_num_threads()
    try:
        for n in sorted({1, threads}):
            torch.set_num_threads(n)
            _run_every_kernel()
    finally:
        torch.set_num_threads(threads)


def _run_every_kernel() -> None:
    D, H, F = 4, 8, 4
    coords = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    corners = torch.arange(16).reshape(2, 8)
    embeddings = torch.randn(16, D, requires_grad=True)
    # A decoder's tensors as FusedField takes them: the SDF head (1 + F, H) and two trunk
    # layers (two, so the backward's ReLU pass between layers runs too).
    head = [torch.randn(1 + F, H, requires_grad=True), torch.randn(1 + F, requires_grad=True)]
    trunk = [torch.randn(H, D, requires_grad=True), torch.randn(H, requires_grad=True),
             torch.randn(H, H, requires_grad=True), torch.randn(H, requires_grad=True)]
    points = torch.rand(5, 3, requires_grad=True)
    voxel_index = torch.zeros(5, dtype=torch.long)
    sdf, hidden = FusedField.apply(points, voxel_index, coords, corners, 1.0, embeddings, *head, *trunk)
    (sdf.sum() + hidden.sum()).backward()
    interpolate_with_slopes(points.detach(), voxel_index, coords, corners, 1.0, embeddings.detach())
    interpolate(points.detach(), voxel_index, coords, corners, 1.0, embeddings.detach())
    band_samples(torch.zeros(2, 3), torch.ones(2, 3), torch.zeros(2), torch.tensor([2, 3]), 0.5, 0.5, 1.0,
                 torch.tensor([0, 1], dtype=torch.int64))
    traverse(torch.zeros(2, 3), torch.ones(2, 3), torch.zeros(2), torch.full((2,), 2.0), torch.ones(2, 3),
             torch.full((2, 3), 2, dtype=torch.int64), torch.tensor([0, 1], dtype=torch.int64), 1.0, 1)
    hash_grid(torch.rand(3, 3), torch.tensor([0.1, 0.05], dtype=torch.float64), torch.randn(12, 2),
              torch.tensor([4, 8]), (1, 3, 5))
    thin_mask(torch.tensor([0, 0, 1]), torch.tensor([0.5, 1.0, 2.0]), torch.tensor([1.0, 3.0]),
              torch.tensor([0, 1]), 0.1, 10.0, 2)
