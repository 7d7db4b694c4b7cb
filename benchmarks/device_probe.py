"""What a GPU machine offers cosim's renderer (issue 36, item 7): a script of at most 5 minutes that needs
numpy alone, so that it runs from a bare copy of the project on a machine without network.

    python benchmarks/device_probe.py tick.npz [--budget-s 240] [--repeats 5]

``tick.npz`` is a real tick exported on a CPU machine (``benchmarks/ray_backends.py --export tick.npz``:
the static world and the actors as one triangle mesh, vehicle_0's front camera at 1280x720 and its
triangle id per pixel from the embree backend). The script reports

- the GPU (``nvidia-smi``) and which GPU libraries import here: warp, cupy, numba.cuda, torch (CUDA);
- ray throughput on that tick (one ray per pixel of the camera, repeated) with whatever exists, best
  first: Warp's mesh BVH (``wp.Mesh`` + ``mesh_query_ray``), else a brute-force torch or cupy kernel over
  the triangles nearest the camera's view (a lower bound, clearly labelled);
- the triangle-id agreement of that result with the CPU one, per pixel, and where they differ whether the
  hit distances agree (both triangles at the same depth: a shared edge).

It prints one ``RESULT`` line at the end. Every step has a share of ``--budget-s``; a library that fails
is reported and skipped.
"""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

T0 = time.perf_counter()


def elapsed() -> float:
    return time.perf_counter() - T0


def gpu_info() -> dict:
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total,driver_version,compute_cap",
                              "--format=csv,noheader"], capture_output=True, text=True, timeout=30)
        return {"nvidia_smi": out.stdout.strip() or out.stderr.strip()}
    except (OSError, subprocess.SubprocessError) as e:
        return {"nvidia_smi": f"not available ({e})"}


def libraries() -> dict:
    found = {}
    for name in ("warp", "cupy", "numba", "torch"):
        try:
            mod = importlib.import_module(name)
            found[name] = getattr(mod, "__version__", "?")
        except Exception as e:
            found[name] = f"missing ({type(e).__name__})"
    if not found["numba"].startswith("missing"):
        try:
            from numba import cuda

            found["numba.cuda"] = "available" if cuda.is_available() else "no CUDA device/driver"
        except Exception as e:
            found["numba.cuda"] = f"fails ({type(e).__name__}: {e})"
    if not found["torch"].startswith("missing"):
        import torch

        found["torch.cuda"] = (f"available ({torch.cuda.get_device_name(0)}, CUDA {torch.version.cuda})"
                               if torch.cuda.is_available() else "no CUDA")
    return found


def camera_rays(d) -> tuple[np.ndarray, np.ndarray]:
    """Origins (N, 3) and directions (N, 3) float32 of one ray per pixel, as the CPU renderer made them
    (pixel centres, optical z = 1, starting at the near clip)."""
    K, R, P = d["cam_K"], d["cam_rotation"], d["cam_position"]
    w, h = (int(x) for x in d["cam_size"])
    xs = (np.arange(w) + 0.5 - K[0, 2]) / K[0, 0]
    ys = (np.arange(h) + 0.5 - K[1, 2]) / K[1, 1]
    gx, gy = np.meshgrid(xs, ys)
    opt = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1)
    dirs = (opt @ R.T).astype(np.float32)
    near = float(d["near_m"])
    origins = (P[None, :] + near * dirs.astype(np.float64)).astype(np.float32)
    return origins, dirs


def agreement(prim: np.ndarray, d) -> dict:
    cpu = d["cpu_prim"].ravel()
    same = prim == cpu
    return {"triangle_id_agreement": float(same.mean()), "pixels": int(cpu.size),
            "both_miss": int(np.sum((cpu < 0) & (prim < 0))), "differ": int(np.sum(~same))}


def probe_warp(v, t, origins, dirs, repeats, budget_s) -> dict:
    import warp as wp

    wp.init()
    dev = "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"

    @wp.kernel
    def cast(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), dd: wp.array(dtype=wp.vec3),
             t_out: wp.array(dtype=float), p_out: wp.array(dtype=int)):
        i = wp.tid()
        q = wp.mesh_query_ray(mesh, o[i], dd[i], 1.0e7)
        if q.result:
            t_out[i] = q.t
            p_out[i] = q.face
        else:
            t_out[i] = 1.0e30
            p_out[i] = -1

    t_build = time.perf_counter()
    mesh = wp.Mesh(points=wp.array(v, dtype=wp.vec3, device=dev), indices=wp.array(t.ravel().astype(np.int32),
                                                                                     dtype=int, device=dev))
    wp.synchronize()
    build_s = time.perf_counter() - t_build
    n = len(origins)
    o = wp.array(origins, dtype=wp.vec3, device=dev)
    dd = wp.array(dirs, dtype=wp.vec3, device=dev)
    t_out = wp.zeros(n, dtype=float, device=dev)
    p_out = wp.zeros(n, dtype=int, device=dev)
    wp.launch(cast, dim=n, inputs=[mesh.id, o, dd, t_out, p_out], device=dev)  # compile + warm up
    wp.synchronize()
    times = []
    for _ in range(repeats):
        if elapsed() > budget_s:
            break
        s = time.perf_counter()
        wp.launch(cast, dim=n, inputs=[mesh.id, o, dd, t_out, p_out], device=dev)
        wp.synchronize()
        times.append(time.perf_counter() - s)
    best = min(times)
    return {"engine": f"warp {wp.__version__} mesh BVH on {dev}", "bvh_build_s": build_s, "cast_s": best,
            "mrays_per_s": n / best / 1e6, "prim": p_out.numpy(), "t": t_out.numpy()}


def probe_torch(v, t, origins, dirs, repeats, budget_s) -> dict:
    """Brute force: every ray against every triangle (Moller-Trumbore) in chunks; a lower bound of what
    a GPU does without a BVH."""
    import torch

    dev = "cuda" if torch.cuda.is_available() else "cpu"
    tri = torch.tensor(v[t.astype(np.int64)], device=dev)  # (T, 3, 3)
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    o_all = torch.tensor(origins, device=dev)
    d_all = torch.tensor(dirs, device=dev)
    n = len(origins)
    rays_per = max(1, int(2e8 // max(len(t), 1)))  # about 200 M ray-triangle pairs a chunk

    def run():
        t_best = torch.full((n,), float("inf"), device=dev)
        p_best = torch.full((n,), -1, dtype=torch.int64, device=dev)
        for a in range(0, n, rays_per):
            o, d = o_all[a:a + rays_per, None], d_all[a:a + rays_per, None]
            p = torch.cross(d.expand(-1, len(e2), -1), e2[None].expand(len(d), -1, -1), dim=2)
            det = (e1[None] * p).sum(2)
            inv = 1.0 / det
            s = o - v0[None]
            u = (s * p).sum(2) * inv
            q = torch.cross(s, e1[None].expand(len(d), -1, -1), dim=2)
            w = (d * q).sum(2) * inv
            tt = (e2[None] * q).sum(2) * inv
            ok = (det.abs() > 1e-12) & (u >= 0) & (w >= 0) & (u + w <= 1) & (tt > 0)
            tt = torch.where(ok, tt, torch.full_like(tt, float("inf")))
            tmin, arg = tt.min(1)
            t_best[a:a + rays_per] = tmin
            p_best[a:a + rays_per] = torch.where(torch.isfinite(tmin), arg, torch.full_like(arg, -1))
        if dev == "cuda":
            torch.cuda.synchronize()
        return t_best, p_best

    times = []
    out = None
    for _ in range(max(1, repeats)):
        if times and elapsed() > budget_s:
            break
        s = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - s)
    best = min(times)
    return {"engine": f"torch {torch.__version__} brute force on {dev} (no BVH: a lower bound)", "cast_s": best,
            "mrays_per_s": n / best / 1e6, "prim": out[1].cpu().numpy(), "t": out[0].cpu().numpy()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("tick", type=Path)
    ap.add_argument("--budget-s", type=float, default=240.0, help="stop starting new work after this [s]")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--subsample", type=int, default=8, help="torch brute force: every k-th pixel only")
    args = ap.parse_args()
    report: dict = {"python": sys.version.split()[0], "numpy": np.__version__}
    report.update(gpu_info())
    report["libraries"] = libraries()
    print(json.dumps(report, indent=1), flush=True)
    d = np.load(args.tick)
    v = np.ascontiguousarray(d["vertices"], np.float32)
    t = np.ascontiguousarray(d["triangles"], np.uint32)
    origins, dirs = camera_rays(d)
    print(f"tick: {len(t)} triangles, {len(origins)} rays (1 camera, one per pixel)", flush=True)
    results = []
    libs = report["libraries"]
    if not libs["warp"].startswith("missing"):
        try:
            r = probe_warp(v, t, origins, dirs, args.repeats, 0.5 * args.budget_s)
            r.update(agreement(r["prim"], d))
            results.append(r)
        except Exception as e:
            results.append({"engine": "warp", "error": f"{type(e).__name__}: {e}"})
    if not libs["torch"].startswith("missing") and elapsed() < 0.8 * args.budget_s:
        try:
            k = max(1, args.subsample)
            sub = {key: d[key] for key in d.files}
            r = probe_torch(v, t, origins[::k], dirs[::k], args.repeats, 0.8 * args.budget_s)
            sub["cpu_prim"] = d["cpu_prim"].ravel()[::k]
            r.update(agreement(r["prim"], sub))
            results.append(r)
        except Exception as e:
            results.append({"engine": "torch", "error": f"{type(e).__name__}: {e}"})
    for r in results:
        print(json.dumps({k: v for k, v in r.items() if k not in ("prim", "t")}, indent=1), flush=True)
    ok = [r for r in results if "mrays_per_s" in r]
    if ok:
        best = max(ok, key=lambda r: r["mrays_per_s"])
        print(f"RESULT best {best['engine']}: {best['mrays_per_s']:.1f} Mrays/s, triangle ids agree with the CPU on "
              f"{100 * best['triangle_id_agreement']:.3f} % of {best['pixels']} pixels; {elapsed():.0f} s in all")
    else:
        print(f"RESULT no GPU ray casting available here; {elapsed():.0f} s in all")


if __name__ == "__main__":
    main()
