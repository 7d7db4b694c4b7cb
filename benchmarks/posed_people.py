"""CPU per walking person per tick for its posed mesh (the template the renderer places), before and after
issue 36: the body built part by part (``person_mesh``, what ``posed_steps`` did behind a cache that a walker
missed nearly every tick) and its faces by ``np.unique(axis=0)``, against the vertices from ``body_points`` in
the builder's order with the per-person topology made once, and the faces by a lexsort. Both in one run,
alternating, on the same people and gait phases; checks that they give the same arrays.

    PYTHONPATH=. .venv/bin/python benchmarks/posed_people.py [--people 20] [--phases 20]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from cosim.sensors import meshes
from cosim.sensors.assets import people


def before(key: str, q_phase: int, q_speed: int) -> tuple[np.ndarray, np.ndarray]:
    p = people.Person.from_key(key)
    v, t, part, grp, _ = people.person_mesh(p, people.walk_pose(q_phase / people.PHASE_STEPS, q_speed / 20))
    tpl = meshes.unit_template(v, t, part, grp)
    n = len(tpl.triangles)
    m = meshes.TriMesh(tpl.vertices, tpl.triangles, np.zeros(n, np.uint8), np.zeros(n, np.uint32),
                       np.zeros((n, 3), np.float32), tpl.part.astype(np.float32), np.zeros(n, np.float32), tpl.group)
    w = m.vertices.astype(np.float64)[m.triangles]
    nrm = np.cross(w[:, 1] - w[:, 0], w[:, 2] - w[:, 0])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    off = (nrm * w[:, 0]).sum(axis=1)
    key_rows = np.column_stack([m.group, np.round(nrm * 1e4), np.round(off * 1e3), m.semantic, m.instance,
                                np.round(m.albedo * 1e4), np.round(m.reflectivity * 1e4), np.round(m.emissive * 1e4)])
    _, face = np.unique(key_rows, axis=0, return_inverse=True)
    return tpl.vertices, face.astype(np.int32).ravel()


def after(key: str, q_phase: int, q_speed: int) -> tuple[np.ndarray, np.ndarray]:
    tpl = meshes._person_template.__wrapped__(key, q_phase, q_speed)
    return tpl.vertices, tpl.faces


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--people", type=int, default=20)
    ap.add_argument("--phases", type=int, default=20)
    args = ap.parse_args()
    keys = [f"bench_{i}" for i in range(args.people)]
    for k in keys:  # per-person set-up (once per episode): not per tick
        after(k, 0, 28)
    cpu = {"before": 0.0, "after": 0.0}
    same = True
    for ph in range(1, args.phases + 1):
        for k in keys:
            out = {}
            for name, fn in (("before", before), ("after", after)):
                c0 = time.process_time()
                out[name] = fn(k, 11 * ph, 28)
                cpu[name] += time.process_time() - c0
            same &= all(np.array_equal(a, b) for a, b in zip(out["before"], out["after"], strict=True))
    n = args.people * args.phases
    print(f"posed person mesh + faces, CPU per person per tick: before {1000 * cpu['before'] / n:.2f} ms, after "
          f"{1000 * cpu['after'] / n:.2f} ms ({cpu['before'] / cpu['after']:.1f}x); same vertices and faces: {same}")


if __name__ == "__main__":
    main()
