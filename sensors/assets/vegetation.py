"""Procedural trees and bushes: a trunk with branches and a porous crown, in several species.

The world layout places a tree as two vegetation prisms, a trunk and a crown (cosim.world.layout);
:func:`tree_mesh` turns such a pair into a tree of one of :data:`SPECIES`, drawn from the tree's position
(the same tree in every episode of a map): a tapered trunk, three to six branches forking into the
crown, and a closed low-poly crown whose shape is the species' (round, conical, columnar, spreading).

A crown is porous: it carries a leaf density [1/m] and the LiDAR transmits each ray through it with the
Beer-Lambert probability exp(-density x chord) (:mod:`cosim.sensors.lidar`), so part of the beams reach
branches, the trunk and what lies behind, as through a real canopy. Cameras see the crown's surface with
the foliage texture. Hedges get a denser foliage.
"""

from __future__ import annotations

import math
import zlib

import numpy as np

from .shapes import Builder, ellipsoid, frustum

#: species: crown shape, leaf density [1/m] (Beer-Lambert extinction; broadleaf crowns in leaf pass a
#: quarter to a half of the beams across their width), branch count
SPECIES: dict[str, tuple[str, float, int]] = {
    "linden": ("round", 0.45, 5),
    "plane": ("spreading", 0.40, 6),
    "spruce": ("cone", 0.55, 3),
    "poplar": ("column", 0.50, 4),
}
#: leaf density of a hedge [1/m]
HEDGE_DENSITY = 1.2

PART_TRUNK, PART_CROWN = 0, 1


def species_of(x: float, y: float) -> str:
    names = sorted(SPECIES)
    return names[zlib.crc32(f"{x:.2f},{y:.2f}".encode()) % len(names)]


def tree_mesh(x: float, y: float, ground_z: float, crown_base_z: float, top_z: float, radius: float,
              species: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    """A tree standing at (x, y) whose crown spans ``crown_base_z``..``top_z`` within ``radius``: vertices,
    triangles, part (PART_TRUNK or PART_CROWN) and group per triangle, and its species."""
    species = species or species_of(x, y)
    shape, _, n_branch = SPECIES[species]
    rng = np.random.default_rng(zlib.crc32(f"tree:{x:.2f},{y:.2f}".encode()))
    b = Builder()
    h = top_z - ground_z
    r_trunk = min(0.2, 0.1 + 0.012 * h)
    base = np.array([x, y, ground_z])
    cz = 0.5 * (crown_base_z + top_z)
    crown_h = top_z - crown_base_z
    trunk_top = top_z - 0.25 * crown_h if shape in ("cone", "column") else cz
    frustum(b, base, (x, y, trunk_top), r_trunk, 0.45 * r_trunk, PART_TRUNK, 6)
    for k in range(n_branch):
        az = 2 * math.pi * (k + rng.uniform(-0.25, 0.25)) / n_branch
        z0 = crown_base_z + (0.1 + 0.5 * k / n_branch) * crown_h
        reach = (0.55 if shape != "column" else 0.35) * radius
        tip = (x + reach * math.cos(az), y + reach * math.sin(az), min(top_z - 0.3, z0 + 0.35 * crown_h))
        frustum(b, (x, y, z0), tip, 0.5 * r_trunk, 0.2 * r_trunk, PART_TRUNK, 5)
    if shape == "round":
        ellipsoid(b, (x, y, cz), (radius, radius, 0.5 * crown_h), PART_CROWN, 5, 8)
    elif shape == "spreading":
        ellipsoid(b, (x, y, cz + 0.1 * crown_h), (radius, 0.92 * radius, 0.42 * crown_h), PART_CROWN, 5, 9)
    elif shape == "column":
        ellipsoid(b, (x, y, cz), (0.55 * radius, 0.55 * radius, 0.5 * crown_h), PART_CROWN, 6, 8)
    else:  # cone: a fir's crown from a wide base to the tip
        frustum(b, (x, y, crown_base_z), (x, y, top_z), 0.9 * radius, 0.05, PART_CROWN, 8)
    v, t, part, grp, _ = b.arrays()
    return v, t, part, grp, species
