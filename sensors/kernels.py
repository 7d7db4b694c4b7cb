"""Compiled per-pixel kernels of camera casting and labelling (numba, ``nogil``).

Open3D holds the GIL while it casts, so numpy passes over whole images in the other render threads
wait for it; these kernels release the GIL and fuse several such passes into one. Each gives exactly
the array its numpy formulation in :mod:`cosim.sensors.camera` gave (same float32 / float64
operations in the same order: numba does not contract multiply-adds without ``fastmath``); the
tests compare them on small synthetic images. Kernels compile on their first call and are cached
on disk (``cache=True``).
"""

from __future__ import annotations

import numba
import numpy as np

#: numpy's floating-point semantics (1 / 0 = inf, no zero-division checks in the loops)
_jit = numba.njit(cache=True, nogil=True, error_model="numpy")


@_jit
def origin_bounds(rays):
    """The smallest and largest x, y, z (3,) each of the origins of ``rays`` (N, 6) (N > 0), in one pass."""
    lo = rays[0, :3].copy()
    hi = rays[0, :3].copy()
    for i in range(1, rays.shape[0]):
        for j in range(3):
            v = rays[i, j]
            if v < lo[j]:
                lo[j] = v
            elif v > hi[j]:
                hi[j] = v
    return lo, hi


@_jit
def rotate_rows(v, rot, out):
    """``out[i] = rot @ v[i]`` for each row of ``v`` (N, 3), the sums in the order of
    :func:`cosim.sensors.rig.rotate`'s numpy expression (the same float64 results)."""
    for i in range(v.shape[0]):
        a, b, c = v[i, 0], v[i, 1], v[i, 2]
        for j in range(3):
            out[i, j] = a * rot[j, 0] + b * rot[j, 1] + c * rot[j, 2]


@_jit
def rays(xs, ys, rotation, position, near):
    """Rays (N, 6) float32 through optical-frame points (xs, ys, 1) (each (N,) float64) of a camera at
    ``position`` (3,) with ``rotation`` (3, 3) map <- optical (float64), starting ``near`` (planar
    depth) in front of the optical centre."""
    n = xs.shape[0]
    out = np.empty((n, 6), np.float32)
    for i in range(n):
        x, y = xs[i], ys[i]
        for k in range(3):
            d = np.float32(rotation[k, 0] * x + rotation[k, 1] * y + rotation[k, 2])
            out[i, 3 + k] = d
            if near != 0.0:
                out[i, k] = np.float32(position[k] + np.float64(np.float32(near) * d))
            else:
                out[i, k] = np.float32(position[k])
    return out


@_jit
def grid_rays(idx, gw, xs, ys, rotation, position, near):
    """:func:`rays` through the sample grid points ``idx`` (flat, row-major over rows of ``gw``) whose
    columns have optical x ``xs`` and rows optical y ``ys``."""
    n = idx.shape[0]
    xv = np.empty(n, np.float64)
    yv = np.empty(n, np.float64)
    for i in range(n):
        r = idx[i] // gw
        xv[i] = xs[idx[i] - r * gw]
        yv[i] = ys[r]
    return rays(xv, yv, rotation, position, near)


@_jit
def shadow_rays(rays, t, gid, normal, sun, bias):
    """Shadow rays (M, 6) float32 of the hits that face the sun, and which rays (M,) they belong to.

    A hit is ray i with finite ``t[i]``; its surface normal ``normal[gid[i]]`` is turned towards the
    ray's side; it faces the sun when that normal has a positive component along ``sun`` (3,)
    float32. The shadow ray starts ``bias`` off the surface along the normal and goes towards the sun.
    """
    n = t.shape[0]
    out = np.empty((n, 6), np.float32)
    which = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        if not np.isfinite(t[i]):
            continue
        g = gid[i]
        nx, ny, nz = normal[g, 0], normal[g, 1], normal[g, 2]
        if nx * rays[i, 3] + ny * rays[i, 4] + nz * rays[i, 5] > 0:
            nx, ny, nz = -nx, -ny, -nz
        if nx * sun[0] + ny * sun[1] + nz * sun[2] > 0:
            out[m, 0] = (rays[i, 0] + t[i] * rays[i, 3]) + bias * nx
            out[m, 1] = (rays[i, 1] + t[i] * rays[i, 4]) + bias * ny
            out[m, 2] = (rays[i, 2] + t[i] * rays[i, 5]) + bias * nz
            out[m, 3] = sun[0]
            out[m, 4] = sun[1]
            out[m, 5] = sun[2]
            which[m] = i
            m += 1
    return out[:m], which[:m]


@_jit
def _inv(t):
    """float32 inverse depth of a sample (0 for a miss)."""
    return np.float32(1.0) / t if np.isfinite(t) else np.float32(0.0)


@_jit
def fill_top(G, T, S, s, gid, depth, lit, with_lit):
    """Dense fill of the whole (H, W) image from the samples ``G``, ``T``, ``S`` ((H + 1, W + 1)) every
    ``s`` px: class and sun from each block's top-left sample, planar depth from the inverse depth
    interpolated bilinearly (first down the block's left and right columns, then across)."""
    h, w = gid.shape
    wgt = np.empty(s, np.float32)
    for k in range(s):
        wgt[k] = np.float32(k) / np.float32(s)
    for bi in range(h // s):
        r0 = bi * s
        for bj in range(w // s):
            c0 = bj * s
            g = G[r0, c0]
            sl = S[r0, c0]
            i00, i01 = _inv(T[r0, c0]), _inv(T[r0, c0 + s])
            i10, i11 = _inv(T[r0 + s, c0]), _inv(T[r0 + s, c0 + s])
            for a in range(s):
                wa = wgt[a]
                left = i00 * (np.float32(1) - wa) + i10 * wa
                right = i01 * (np.float32(1) - wa) + i11 * wa
                for k in range(s):
                    v = left * (np.float32(1) - wgt[k]) + right * wgt[k]
                    depth[r0 + a, c0 + k] = np.float32(1) / v  # 1 / 0 = inf: all corners missed
                    gid[r0 + a, c0 + k] = g
                    if with_lit:
                        lit[r0 + a, c0 + k] = sl


@_jit
def _fill_block(G, T, S, r0, c0, s, wgt, gid, depth, lit, with_lit):
    """One coherent block of ``s`` px at (r0, c0): inverse depth bilinear over its four corners."""
    i0, i1 = _inv(T[r0, c0]), _inv(T[r0, c0 + s])
    i2, i3 = _inv(T[r0 + s, c0]), _inv(T[r0 + s, c0 + s])
    g = G[r0, c0]
    sl = S[r0, c0]
    for a in range(s):
        fa = wgt[a]
        ga = np.float32(1) - fa
        for b in range(s):
            fb = wgt[b]
            gb = np.float32(1) - fb
            v = i0 * ga * gb
            v += i1 * ga * fb
            v += i2 * fa * gb
            v += i3 * fa * fb
            depth[r0 + a, c0 + b] = np.float32(1.0) / v  # v >= 0; 1 / 0 = inf
            gid[r0 + a, c0 + b] = g
            if with_lit:
                lit[r0 + a, c0 + b] = sl


@_jit
def _clamp(g, n):
    """``g`` clamped to 0 .. n - 1 (a sample's triangle index as an index into per-triangle tables)."""
    return 0 if g < 0 else (n - 1 if g >= n else g)


@_jit
def refine_level(G, T, S, face, s, top, parent_mixed, forced, fill, gid, depth, lit, with_lit):
    """One level of the quadtree: blocks of ``s`` px (those whose parent block of 2 ``s`` was mixed,
    every block at the top level) are coherent when their four corner samples share a face (and the
    sun's reaching them) and they are not ``forced``; coherent ones are filled when ``fill``.

    Returns the mixed blocks (H / s, W / s) bool and the flat indices (into the (H + 1) x (W + 1)
    sample grid) of their new samples: all centres, then top midpoints, left midpoints, and the
    bottom and right midpoints of blocks whose neighbour there is not mixed (it adds them itself)."""
    hb, wb = forced.shape
    gw = G.shape[1]
    nf = face.shape[0]
    mixed = np.zeros((hb, wb), np.bool_)
    wgt = np.empty(s, np.float32)
    for k in range(s):
        wgt[k] = np.float32(k) / np.float32(s)
    n_mixed = 0
    for bi in range(hb):
        r0 = bi * s
        for bj in range(wb):
            if not top and not parent_mixed[bi // 2, bj // 2]:
                continue
            c0 = bj * s
            same = not forced[bi, bj]
            if same:
                f0 = face[_clamp(G[r0, c0], nf)]
                same = (f0 == face[_clamp(G[r0, c0 + s], nf)] and f0 == face[_clamp(G[r0 + s, c0], nf)]
                        and f0 == face[_clamp(G[r0 + s, c0 + s], nf)])
            if same and with_lit:
                l0 = S[r0, c0]
                same = l0 == S[r0, c0 + s] and l0 == S[r0 + s, c0] and l0 == S[r0 + s, c0 + s]
            if same:
                if fill:
                    _fill_block(G, T, S, r0, c0, s, wgt, gid, depth, lit, with_lit)
            else:
                mixed[bi, bj] = True
                n_mixed += 1
    half = s // 2
    n_below = n_right = 0
    for bi in range(hb):
        for bj in range(wb):
            if mixed[bi, bj]:
                if bi + 1 >= hb or not mixed[bi + 1, bj]:
                    n_below += 1
                if bj + 1 >= wb or not mixed[bi, bj + 1]:
                    n_right += 1
    cand = np.empty(3 * n_mixed + n_below + n_right, np.int64)
    k = 0
    for part in range(5):
        for bi in range(hb):
            r0 = bi * s
            for bj in range(wb):
                if not mixed[bi, bj]:
                    continue
                c0 = bj * s
                if part == 0:
                    cand[k] = (r0 + half) * gw + c0 + half
                elif part == 1:
                    cand[k] = r0 * gw + c0 + half
                elif part == 2:
                    cand[k] = (r0 + half) * gw + c0
                elif part == 3:
                    if bi + 1 < hb and mixed[bi + 1, bj]:
                        continue
                    cand[k] = (r0 + s) * gw + c0 + half
                else:
                    if bj + 1 < wb and mixed[bi, bj + 1]:
                        continue
                    cand[k] = (r0 + half) * gw + c0 + s
                k += 1
    return mixed, cand


@_jit
def copy_mixed(mixed, G, T, S, gid, depth, lit, with_lit):
    """The pixels of the mixed 2 px blocks are samples themselves: copy them."""
    hb, wb = mixed.shape
    for bi in range(hb):
        for bj in range(wb):
            if mixed[bi, bj]:
                for a in range(2):
                    r = 2 * bi + a
                    for b in range(2):
                        c = 2 * bj + b
                        gid[r, c] = G[r, c]
                        depth[r, c] = T[r, c]
                        if with_lit:
                            lit[r, c] = S[r, c]


@_jit
def gather(index, table):
    """``table[index]`` for an (H, W) index image (one pass, no bounds wrap: indices are valid)."""
    out = np.empty(index.shape, table.dtype)
    for i in range(index.shape[0]):
        for j in range(index.shape[1]):
            out[i, j] = table[index[i, j]]
    return out


@_jit
def gather2(index, table_a, table_b):
    """``(table_a[index], table_b[index])`` in one pass over an (H, W) index image."""
    a = np.empty(index.shape, table_a.dtype)
    b = np.empty(index.shape, table_b.dtype)
    for i in range(index.shape[0]):
        for j in range(index.shape[1]):
            g = index[i, j]
            a[i, j] = table_a[g]
            b[i, j] = table_b[g]
    return a, b


@_jit
def depth_codes(depth, inv_quantum, codes, escapes):
    """The 2-bit codes ``codes`` (ceil(H W / 4),) uint8, zeroed by the caller, and the escapes ``escapes``
    (H W,) uint32 of ``cosim-depth`` for ``depth`` (H, W) float32 [m]: counts rint(depth * ``inv_quantum``)
    (float32; 0 where not finite), residuals against left + up - upper left, zigzag-coded, then coded
    (:func:`cosim.depth.depth_codes` of :func:`cosim.depth.depth_residuals` in one pass). Returns the
    number of escapes written."""
    h, w = depth.shape
    up = np.zeros(w, np.int64)
    k = 0
    m = 0
    for i in range(h):
        left = np.int64(0)
        upleft = np.int64(0)
        for j in range(w):
            v = np.rint(depth[i, j] * inv_quantum)
            c = np.int64(v) if np.isfinite(v) else np.int64(0)
            r = c - up[j] - left + upleft
            z = ((r << 1) ^ (r >> 63)) & 0xFFFFFFFF
            if z >= 3:
                escapes[m] = z - 3
                m += 1
                z = 3
            codes[k >> 2] |= np.uint8(z << (2 * (k & 3)))
            k += 1
            upleft = up[j]
            up[j] = c
            left = c
    return m
