"""numba kernels on numpy arrays: the field's per-sample work fused into one pass each way.

Importing this module imports numba; ``slam.kernels`` only does so when the numba path is
selected. Every kernel works on float32 arrays and int64 indices, writes into arrays the
caller allocates, and runs its outer loop over ``prange`` (the caller sets numba's thread
count to torch's). Each kernel is compiled twice: parallel, and serial for a process that
has one thread (``_TwoWays``), so that such a process never starts numba's OpenMP pool,
whose idle workers spin: the tracking and mapping processes on two cores ran at half speed
(decisions.md#kernels.serial_copies). Samples
are processed in contiguous chunks, one per thread, so that a kernel that scatters into
embedding rows can give each chunk its own accumulator: no atomics, and the sum is the same
for the same thread count.

Corner c of a voxel sits at offset (c & 1, (c >> 1) & 1, (c >> 2) & 1), as in
``slam.render.trilinear_weights``; ``local`` is the position inside the voxel in [0, 1]^3.

``cache=True`` keeps the compiled code next to this file (or in numba's user cache when the
package directory is read-only), so only the first process on a machine compiles.
"""

from __future__ import annotations

import functools
import inspect
import types

import numpy as np
from numba import njit, prange

from ..voxels import _dilate as spread_bits

# Reassociation lets LLVM vectorise the reductions; no nnan/ninf, so a NaN still propagates
# as it does in torch; no arcp, so points / voxel_size rounds as torch's division does (a
# sample on a voxel face must land on the same side of the clamp).
_FASTMATH = {"reassoc", "contract", "nsz"}
_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _local(points, i, coords, v, voxel_size, local, inside):
    """local[a] = clamp(points[i, a] / voxel_size - coords[v, a], 0, 1); inside[a] = the clamp
    passes the gradient (torch's clamp: min <= x <= max)."""
    for a in range(3):
        x = points[i, a] / voxel_size - coords[v, a]
        inside[a] = x >= _ZERO and x <= _ONE
        local[a] = min(max(x, _ZERO), _ONE)


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _corner_weights(local, w):
    """w[c] = trilinear weight of corner c, multiplied in ``trilinear_weights``' order (z y x)."""
    for c in range(8):
        fx = local[0] if c & 1 else _ONE - local[0]
        fy = local[1] if (c >> 1) & 1 else _ONE - local[1]
        fz = local[2] if (c >> 2) & 1 else _ONE - local[2]
        w[c] = fz * fy * fx


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _corner_weight_slopes(local, dw):
    """dw[a, c] = d w[c] / d local[a]."""
    for c in range(8):
        bx, by, bz = c & 1, (c >> 1) & 1, (c >> 2) & 1
        fx = local[0] if bx else _ONE - local[0]
        fy = local[1] if by else _ONE - local[1]
        fz = local[2] if bz else _ONE - local[2]
        sx = _ONE if bx else -_ONE
        sy = _ONE if by else -_ONE
        sz = _ONE if bz else -_ONE
        dw[0, c] = fz * fy * sx
        dw[1, c] = fz * sy * fx
        dw[2, c] = sz * fy * fx


@njit(cache=True, inline="always")
def _scratch():
    """One thread's per-sample buffers: local (3,), inside (3,), weights (8,), slopes (3, 8)."""
    return (np.empty(3, np.float32), np.empty(3, np.bool_), np.empty(8, np.float32),
            np.empty((3, 8), np.float32))


def _chunk(n, chunks, t):
    return n * t // chunks, n * (t + 1) // chunks


_chunk = njit(cache=True, inline="always")(_chunk)


class _TwoWays:
    """A kernel compiled parallel and serial; a call whose ``chunks`` is 1 takes the serial
    one, where ``prange`` is a plain ``range`` and no thread pool is involved. The serial
    copy has its own qualified name, so numba's disk cache keeps the two apart."""

    def __init__(self, fn, fastmath=_FASTMATH):
        serial = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__ + "_serial", fn.__defaults__,
                                    fn.__closure__)
        serial.__qualname__ = fn.__qualname__ + "_serial"
        self.parallel = njit(parallel=True, cache=True, fastmath=fastmath)(fn)
        self.serial = njit(cache=True, fastmath=fastmath)(serial)
        self._chunks_at = list(inspect.signature(fn).parameters).index("chunks")
        functools.update_wrapper(self, fn)

    def __call__(self, *args):
        kernel = self.serial if args[self._chunks_at] == 1 else self.parallel
        return kernel(*args)


@_TwoWays
def interpolate(points, voxel_index, coords, corners, embeddings, voxel_size, chunks, x_out):
    """Trilinear interpolation of the corner embeddings, per sample.

    points (S, 3), voxel_index (S,), coords (Nv, 3), corners (Nv, 8), embeddings (Nc, D)
    -> x_out (S, D). The first layer stays a matrix product: a per-sample 16 x H product
    here measured 7x slower than MKL's (23k samples: 7.2 against 1.0 ms).
    """
    S, D = x_out.shape
    for t in prange(chunks):
        lo, hi = _chunk(S, chunks, t)
        local, inside, w, _ = _scratch()
        for i in range(lo, hi):
            v = voxel_index[i]
            _local(points, i, coords, v, voxel_size, local, inside)
            _corner_weights(local, w)
            for d in range(D):
                x_out[i, d] = _ZERO
            for c in range(8):
                row = corners[v, c]
                wc = w[c]
                for d in range(D):
                    x_out[i, d] += wc * embeddings[row, d]


@_TwoWays
def head_backward(g_sdf, g_hidden, hidden, w_row, chunks, g_z):
    """Gradient at the last trunk layer's pre-activation.

    g_z (S, H) = (g_hidden + g_sdf w_row^T) * (hidden > 0): the SDF row ``hidden @ w_row``
    and the hidden output share the ReLU. g_sdf (S,), g_hidden (S, H) or (0, 0) when the
    hidden output got no gradient, hidden (S, H) after the ReLU, w_row (H,).
    """
    S, H = g_z.shape
    has_hidden = g_hidden.shape[0] == S
    for t in prange(chunks):
        lo, hi = _chunk(S, chunks, t)
        for i in range(lo, hi):
            gs = g_sdf[i]
            for j in range(H):
                g = gs * w_row[j]
                if has_hidden:
                    g += g_hidden[i, j]
                g_z[i, j] = g if hidden[i, j] > _ZERO else _ZERO


@_TwoWays
def relu_backward_(g, h, chunks):
    """g (S, H) *= (h > 0) in place: the gradient through a ReLU whose output is h."""
    S, H = g.shape
    for t in prange(chunks):
        lo, hi = _chunk(S, chunks, t)
        for i in range(lo, hi):
            for j in range(H):
                if not h[i, j] > _ZERO:
                    g[i, j] = _ZERO


@_TwoWays
def interpolate_backward(g_x, points, voxel_index, coords, corners, embeddings, voxel_size, chunks,
                         need_emb, need_points, g_emb_parts, g_points):
    """Backward of ``interpolate``: g_x (S, D) the gradient at the interpolated embedding.

    With ``need_emb`` each chunk t adds its samples' embedding gradient straight into
    g_emb_parts[t] (chunks, Nc, D), zeroed by the caller (no (S, 8, D) products, no sort).
    With ``need_points`` g_points (S, 3) gets d loss / d point (zero on an axis where the
    local coordinate was clamped, as torch's clamp does).
    """
    S, D = g_x.shape
    for t in prange(chunks):
        lo, hi = _chunk(S, chunks, t)
        local, inside, w, dw = _scratch()
        for i in range(lo, hi):
            v = voxel_index[i]
            _local(points, i, coords, v, voxel_size, local, inside)
            _corner_weights(local, w)
            if need_emb:
                for c in range(8):
                    row = corners[v, c]
                    wc = w[c]
                    for d in range(D):
                        g_emb_parts[t, row, d] += wc * g_x[i, d]
            if need_points:
                _corner_weight_slopes(local, dw)
                ga0 = _ZERO
                ga1 = _ZERO
                ga2 = _ZERO
                for c in range(8):
                    row = corners[v, c]
                    dot = _ZERO
                    for d in range(D):
                        dot += embeddings[row, d] * g_x[i, d]
                    ga0 += dw[0, c] * dot
                    ga1 += dw[1, c] * dot
                    ga2 += dw[2, c] * dot
                g_points[i, 0] = ga0 / voxel_size if inside[0] else _ZERO
                g_points[i, 1] = ga1 / voxel_size if inside[1] else _ZERO
                g_points[i, 2] = ga2 / voxel_size if inside[2] else _ZERO


@_TwoWays
def interpolate_with_slopes(points, voxel_index, coords, corners, embeddings, voxel_size, chunks,
                            feats, dfeats):
    """Trilinear interpolation and its spatial derivative, forward only.

    -> feats (S, D) and dfeats (S, 3, D) = d feats / d point per metre (the clamp ignored, as
    ``slam.render.interpolate_with_gradient`` does).
    """
    S, D = feats.shape
    for t in prange(chunks):
        lo, hi = _chunk(S, chunks, t)
        local, inside, w, dw = _scratch()
        acc = np.empty((4, D), np.float32)
        for i in range(lo, hi):
            v = voxel_index[i]
            _local(points, i, coords, v, voxel_size, local, inside)
            _corner_weights(local, w)
            _corner_weight_slopes(local, dw)
            acc[:] = _ZERO
            for c in range(8):
                row = corners[v, c]
                w0, w1, w2, w3 = w[c], dw[0, c] / voxel_size, dw[1, c] / voxel_size, dw[2, c] / voxel_size
                for d in range(D):
                    e = embeddings[row, d]
                    acc[0, d] += w0 * e
                    acc[1, d] += w1 * e
                    acc[2, d] += w2 * e
                    acc[3, d] += w3 * e
            for d in range(D):
                feats[i, d] = acc[0, d]
                dfeats[i, 0, d] = acc[1, d]
                dfeats[i, 1, d] = acc[2, d]
                dfeats[i, 2, d] = acc[3, d]


# ------------------------------------------------------------ band sampling (views)
_MORTON_OFFSET = 1 << 20
_COORD_LIMIT = (1 << 20) - 1


# ``slam.voxels._dilate`` uses only integer operators, so numba compiles the same function
# for one int64 at a time.
_dilate = njit(cache=True, inline="always")(spread_bits)


@njit(cache=True, inline="always")
def _voxel_coordinate(x, voxel_size):
    """floor(x / voxel_size) clamped to the Morton range, as ``sample_points_in_band``."""
    i = np.int64(np.floor(x / voxel_size))
    return min(max(i, -_MORTON_OFFSET), _COORD_LIMIT) + _MORTON_OFFSET


@njit(cache=True, inline="always")
def _find(sorted_codes, code):
    """Index of ``code`` in ``sorted_codes`` or -1 (``slam.voxels.lookup_sorted``)."""
    lo, hi = 0, sorted_codes.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if sorted_codes[mid] < code:
            lo = mid + 1
        else:
            hi = mid
    if lo < sorted_codes.shape[0] and sorted_codes[lo] == code:
        return lo
    return -1


@njit(cache=True, inline="always")
def _voxel_at(x, y, z, voxel_size, voxel_codes):
    """Index in ``voxel_codes`` of the voxel holding the point (x, y, z), or -1."""
    code = (_dilate(_voxel_coordinate(x, voxel_size))
            | (_dilate(_voxel_coordinate(y, voxel_size)) << 1)
            | (_dilate(_voxel_coordinate(z, voxel_size)) << 2))
    return _find(voxel_codes, code)


def band_samples(origins, dirs, k0, counts, first, step, offset, voxel_size, voxel_codes, chunks,
                 ray_out, t_out, voxel_out):
    """Every grid point ``t = (k0 + j + offset) * step``, j < counts, of every ray, and the
    voxel it lies in: ``slam.render.sample_points_in_band`` before it drops the misses.

    origins, dirs (R, 3) float32; k0 (R,) float32; counts, first (R,) int64 (first: where a
    ray's samples start in the outputs); voxel_codes (Nv,) sorted int64 -> ray_out (S,)
    int64, t_out (S,) float32, voxel_out (S,) int64 (-1: no voxel). Compiled without fastmath, so every
    product and sum rounds as torch's separate operations do (no fused multiply-add): a
    sample on a voxel face lands in the same voxel.
    """
    R = origins.shape[0]
    step32, offset32 = np.float32(step), np.float32(offset)
    for th in prange(chunks):
        lo, hi = _chunk(R, chunks, th)
        for r in range(lo, hi):
            base = first[r]
            for j in range(counts[r]):
                t = (k0[r] + np.float32(j) + offset32) * step32
                x = origins[r, 0] + t * dirs[r, 0]
                y = origins[r, 1] + t * dirs[r, 1]
                z = origins[r, 2] + t * dirs[r, 2]
                ray_out[base + j] = r
                t_out[base + j] = t
                voxel_out[base + j] = _voxel_at(x, y, z, voxel_size, voxel_codes)


band_samples = _TwoWays(band_samples, fastmath=False)


# ------------------------------------------------------------ ray-voxel traversal
def traverse(origins, dirs, near, far, k_lo, axis_counts, first, voxel_size, voxel_codes, max_hits, max_bounds,
             chunks, ray_out, voxel_out, t_in_out, t_out_out):
    """``slam.render.ray_voxel_intersections`` after its ``clip_to_box``, one ray at a time:
    the face planes each axis crosses in (near, far), sorted with near and far, capped at far;
    every interval longer than 1e-7 whose midpoint lies in an allocated voxel is a hit, the
    first ``max_hits`` of them (0: all) kept.

    origins, dirs (R, 3) float32; near, far (R,) float32; k_lo (R, 3) float32 and axis_counts
    (R, 3) int64: the index of the first plane crossed per axis and how many (the torch side's
    ``_plane_range``); first (R,) int64: where a ray's slots start in
    the outputs; max_bounds: the most bounds of any ray -> hits written from ``first[r]`` on:
    ray_out (H,) int64 (slots left at -1 are unused), voxel_out (H,) int64, t_in_out,
    t_out_out (H,) float32. Compiled without fastmath so every operation rounds as torch's
    separate operators do: the same intervals and voxels to the bit.
    """
    R = origins.shape[0]
    eps, half = np.float32(1e-7), np.float32(0.5)
    for th in prange(chunks):
        lo, hi = _chunk(R, chunks, th)
        bounds = np.empty(max_bounds, np.float32)
        for r in range(lo, hi):
            n = 0
            bounds[n] = near[r]
            n += 1
            for a in range(3):
                count = axis_counts[r, a]
                if count == 0:
                    continue
                o, d = origins[r, a], dirs[r, a]
                for j in range(count):
                    plane = (k_lo[r, a] + np.float32(j)) * voxel_size
                    bounds[n] = (plane - o) / d
                    n += 1
            bounds[n] = far[r]
            n += 1
            # Insertion sort: each axis's crossings are already monotonic, n is a few dozen.
            for i in range(1, n):
                v = bounds[i]
                k = i - 1
                while k >= 0 and bounds[k] > v:
                    bounds[k + 1] = bounds[k]
                    k -= 1
                bounds[k + 1] = v
            for i in range(n):
                bounds[i] = min(bounds[i], far[r])
            slot = first[r]
            hits = 0
            for i in range(n - 1):
                if max_hits > 0 and hits == max_hits:
                    break
                t0, t1 = bounds[i], bounds[i + 1]
                if not t1 > t0 + eps:
                    continue
                mid = half * (t0 + t1)
                x = origins[r, 0] + mid * dirs[r, 0]
                y = origins[r, 1] + mid * dirs[r, 1]
                z = origins[r, 2] + mid * dirs[r, 2]
                v = _voxel_at(x, y, z, voxel_size, voxel_codes)
                if v < 0:
                    continue
                ray_out[slot + hits] = r
                voxel_out[slot + hits] = v
                t_in_out[slot + hits] = t0
                t_out_out[slot + hits] = t1
                hits += 1


traverse = _TwoWays(traverse, fastmath=False)


# ------------------------------------------------------------ thinned mapping samples
@njit(cache=True)
def thin_mask(ray_index, t, depth, phase, truncation, max_depth, stride, keep_out, stands_out):
    """``slam.render.thin_training_samples``' choice, one pass over samples sorted by ray:
    keep_out (S,) bool, stands_out (S,) float32 (the stride for kept free-space samples).

    ray_index (S,) int64, t (S,) float32, depth (R,) float32, phase (R,) int64; truncation
    and max_depth float32, so every comparison rounds as torch's float32 ones do.
    """
    low = np.float32(0.01)
    prev, rank = -1, 0
    for i in range(ray_index.shape[0]):
        r = ray_index[i]
        if r != prev:
            prev, rank = r, 0
        d = depth[r]
        valid = d > low and d < max_depth
        front = valid and t[i] < d - truncation
        behind = valid and t[i] > d + truncation
        keep_out[i] = not behind and (not front or (rank + phase[r]) % stride == 0)
        stands_out[i] = np.float32(stride) if front else np.float32(1.0)
        rank += 1


@_TwoWays
def hash_grid(points, cells, tables, rows, offsets, primes, chunks, out):
    """The fine colour level's features (``slam.fine_color.hash_features``), forward only.

    points (N, 3) float32, cells (L,) float64 cell edges, tables (R, F) float32 holding the
    levels' tables one after another, rows (L,) int64 each level's size (a power of two),
    offsets (L,) int64 its first row, primes (3,) int64 -> out (N, L * F): per level, the
    trilinear sum over the point's cell's 8 corners of the rows their spatial hash names.
    """
    N = out.shape[0]
    L = cells.shape[0]
    F = tables.shape[1]
    for t in prange(chunks):
        lo, hi = _chunk(N, chunks, t)
        base = np.empty(3, np.int64)
        frac = np.empty(3, np.float32)
        for i in range(lo, hi):
            for level in range(L):
                for a in range(3):
                    x = np.float64(points[i, a]) / cells[level]
                    b = np.floor(x)
                    base[a] = np.int64(b)
                    frac[a] = np.float32(x - b)
                for f in range(F):
                    out[i, level * F + f] = _ZERO
                for c in range(8):
                    ca, cb, cc = (c >> 2) & 1, (c >> 1) & 1, c & 1
                    h = ((base[0] + ca) * primes[0]) ^ ((base[1] + cb) * primes[1]) ^ ((base[2] + cc) * primes[2])
                    row = offsets[level] + (h & (rows[level] - 1))
                    w0 = frac[0] if ca else _ONE - frac[0]
                    w1 = frac[1] if cb else _ONE - frac[1]
                    w2 = frac[2] if cc else _ONE - frac[2]
                    w = w0 * w1 * w2
                    for f in range(F):
                        out[i, level * F + f] += w * tables[row, f]
