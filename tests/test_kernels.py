"""The compiled camera kernels give exactly what their numpy formulations give (small synthetic images)."""

from __future__ import annotations

import numpy as np
import pytest
from cosim.sensors import kernels

H, W, TOP = 16, 24, 8


@pytest.fixture(scope="module")
def samples():
    """A (H + 1) x (W + 1) sample grid: triangle index, depth (some misses), sun reaching it."""
    rng = np.random.default_rng(7)
    G = rng.integers(0, 4, (H + 1, W + 1)).astype(np.int32)
    G[::TOP, ::TOP] = rng.integers(0, 2, G[::TOP, ::TOP].shape)  # coarse corners often agree
    T = rng.uniform(1.0, 80.0, (H + 1, W + 1)).astype(np.float32)
    T[rng.random(T.shape) < 0.1] = np.inf
    S = rng.random(T.shape) < 0.8
    T[:TOP + 1, :TOP + 1] = np.inf  # a block of sky
    G[TOP:, TOP:] = rng.integers(0, 2, G[TOP:, TOP:].shape)  # one face (triangles 0 and 1), in the sun
    S[TOP:, TOP:] = True
    face = np.array([0, 0, 1, 2], np.int32)  # triangles 0 and 1 are one face
    return G, T, S, face


def _inv(t):
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(t), 1.0 / t, 0.0).astype(np.float32)


def test_fill_top_matches_numpy(samples):
    G, T, S, _ = samples
    s, wb = TOP, W // TOP
    gid, depth, lit = np.empty((H, W), np.int32), np.empty((H, W), np.float32), np.empty((H, W), bool)
    kernels.fill_top(G, T, S, s, gid, depth, lit, True)
    inv = _inv(T[::s, ::s])
    wgt = np.arange(s, dtype=np.float32) / s
    rows = (inv[:-1, None, :] * (1 - wgt)[None, :, None] + inv[1:, None, :] * wgt[None, :, None]).reshape(H, wb + 1)
    ref = np.empty((H, wb, s), np.float32)
    for k in range(s):
        ref[:, :, k] = rows[:, :-1] * (1 - wgt[k]) + rows[:, 1:] * wgt[k]
    with np.errstate(divide="ignore"):
        ref = np.float32(1.0) / ref.reshape(H, W)
    np.testing.assert_array_equal(depth, ref)
    np.testing.assert_array_equal(gid, np.repeat(np.repeat(G[::s, ::s][:-1, :-1], s, 0), s, 1))
    np.testing.assert_array_equal(lit, np.repeat(np.repeat(S[::s, ::s][:-1, :-1], s, 0), s, 1))
    assert np.isinf(depth).any() and np.isfinite(depth).any()


def test_refine_level_matches_numpy(samples):
    G, T, S, face = samples
    s = 4
    hb, wb = H // s, W // s
    parent = np.array([[True, False, True], [False, True, True]])
    forced = np.zeros((hb, wb), bool)
    forced[1, 1] = True
    gid, depth, lit = np.zeros((H, W), np.int32), np.zeros((H, W), np.float32), np.zeros((H, W), bool)
    mixed, cand = kernels.refine_level(G, T, S, face, s, False, parent, forced, True, gid, depth, lit, True)
    # numpy: corner agreement on face and sun
    fs, ss = face[G[::s, ::s]], S[::s, ::s]
    same = (fs[:-1, :-1] == fs[:-1, 1:]) & (fs[:-1, :-1] == fs[1:, :-1]) & (fs[:-1, :-1] == fs[1:, 1:])
    same &= (ss[:-1, :-1] == ss[:-1, 1:]) & (ss[:-1, :-1] == ss[1:, :-1]) & (ss[:-1, :-1] == ss[1:, 1:])
    active = np.repeat(np.repeat(parent, 2, 0), 2, 1)
    coherent = active & same & ~forced
    np.testing.assert_array_equal(mixed, active & ~coherent)
    assert coherent.any() and mixed.any()
    # coherent blocks: inverse depth bilinear over the corners
    f = np.arange(s, dtype=np.float32) / s
    for bi, bj in zip(*np.nonzero(coherent), strict=True):
        r0, c0 = bi * s, bj * s
        i0, i1, i2, i3 = (_inv(T[r, c]) for r, c in ((r0, c0), (r0, c0 + s), (r0 + s, c0), (r0 + s, c0 + s)))
        val = (i0 * (1 - f)[:, None] * (1 - f)[None, :] + i1 * (1 - f)[:, None] * f[None, :]
               + i2 * f[:, None] * (1 - f)[None, :] + i3 * f[:, None] * f[None, :])
        with np.errstate(divide="ignore"):
            ref = np.where(val > 0, 1.0 / val, np.inf).astype(np.float32)
        np.testing.assert_array_equal(depth[r0:r0 + s, c0:c0 + s], ref)
        assert (gid[r0:r0 + s, c0:c0 + s] == G[r0, c0]).all() and (lit[r0:r0 + s, c0:c0 + s] == S[r0, c0]).all()
    untouched = ~np.repeat(np.repeat(coherent, s, 0), s, 1)
    assert (depth[untouched] == 0).all()
    # new samples: centres, top and left midpoints, then bottom and right ones not shared with a mixed neighbour
    bi, bj = np.nonzero(mixed)
    half, gw = s // 2, W + 1
    below = np.ones_like(mixed)
    below[:-1] = ~mixed[1:]
    right = np.ones_like(mixed)
    right[:, :-1] = ~mixed[:, 1:]
    r0, c0 = bi * s, bj * s
    db, dr = below[bi, bj], right[bi, bj]
    ref = np.concatenate([(r0 + half) * gw + c0 + half, r0 * gw + c0 + half, (r0 + half) * gw + c0,
                          (r0[db] + s) * gw + c0[db] + half, (r0[dr] + half) * gw + c0[dr] + s])
    np.testing.assert_array_equal(cand, ref)


def test_rays_and_shadow_rays_match_numpy():
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    pos = rng.uniform(-50, 50, 3)
    xs, ys = rng.uniform(-1, 1, 500), rng.uniform(-0.6, 0.6, 500)
    rays = kernels.rays(xs, ys, q, pos, 0.5)
    ref = np.empty((500, 6), np.float32)
    for k in range(3):
        ref[:, 3 + k] = q[k, 0] * xs + q[k, 1] * ys + q[k, 2]
        ref[:, k] = pos[k] + 0.5 * ref[:, 3 + k]
    np.testing.assert_array_equal(rays, ref)
    gw = 9
    idx = rng.integers(0, 9 * gw, 40)
    gx, gy = rng.uniform(-1, 1, gw), rng.uniform(-1, 1, 9)
    np.testing.assert_array_equal(kernels.grid_rays(idx, gw, gx, gy, q, pos, 0.0),
                                  kernels.rays(gx[idx % gw], gy[idx // gw], q, pos, 0.0))

    normal = rng.standard_normal((30, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    t = rng.uniform(1, 40, 500).astype(np.float32)
    t[::7] = np.inf
    gid = rng.integers(0, 30, 500).astype(np.int32)
    sun = np.array([0.3, -0.4, 0.866], np.float32)
    sh, which = kernels.shadow_rays(rays, t, gid, normal, sun, np.float32(0.02))
    idx = np.nonzero(np.isfinite(t))[0]
    n = normal[gid[idx]]
    n[(n * rays[idx, 3:]).sum(axis=1) > 0] *= -1
    facing = np.nonzero(n @ sun > 0)[0]
    k = idx[facing]
    np.testing.assert_array_equal(which, k)
    np.testing.assert_array_equal(sh[:, :3], rays[k, :3] + t[k, None] * rays[k, 3:] + np.float32(0.02) * n[facing])
    assert (sh[:, 3:] == sun).all() and 0 < len(k) < len(idx)


def test_gathers_match_numpy():
    rng = np.random.default_rng(5)
    gid = rng.integers(0, 6, (12, 20)).astype(np.int32)
    a = rng.integers(0, 255, 6).astype(np.uint8)
    b = rng.integers(0, 2**31, 6).astype(np.uint32)
    sa, sb = kernels.gather2(gid, a, b)
    np.testing.assert_array_equal(sa, np.take(a, gid))
    np.testing.assert_array_equal(sb, np.take(b, gid))
    np.testing.assert_array_equal(kernels.gather(gid, b), np.take(b, gid))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rotate_rows_matches_numpy(dtype):
    """``rig.rotate`` runs the kernel on tall arrays: the same float64 (or float32 x float64) results as the
    numpy expression it stands for, for contiguous, strided and broadcast rows."""
    from cosim.sensors.rig import ROTATE_KERNEL_ROWS, rotate

    rng = np.random.default_rng(3)
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    tall = rng.normal(size=(ROTATE_KERNEL_ROWS + 17, 6)).astype(dtype)
    for v in (np.ascontiguousarray(tall[:, :3]), tall[:, 3:], np.broadcast_to(tall[0, :3], (len(tall), 3))):
        ref = v[:, 0:1] * rot[:, 0] + v[:, 1:2] * rot[:, 1] + v[:, 2:3] * rot[:, 2]
        got = rotate(v, rot)
        assert got.dtype == ref.dtype == np.float64 and np.array_equal(got, ref)
    assert np.allclose(rotate(tall[:5, :3], rot), tall[:5, :3] @ rot.T)  # below the threshold: numpy


def test_origin_bounds_match_numpy():
    rng = np.random.default_rng(5)
    rays = rng.normal(size=(1001, 6)).astype(np.float32)
    lo, hi = kernels.origin_bounds(rays)
    assert np.array_equal(lo, rays[:, :3].min(0)) and np.array_equal(hi, rays[:, :3].max(0))
    one = kernels.origin_bounds(rays[:1])
    assert np.array_equal(one[0], rays[0, :3]) and np.array_equal(one[1], rays[0, :3])
