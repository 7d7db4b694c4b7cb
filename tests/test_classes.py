"""The class table is the one place classes live: docs, colours, meshes, BEV layers and box colours follow it."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from cosim.classes import OBJECT_CLASSES, SEMANTIC_CLASSES, SEMANTIC_COLOURS, class_table, semantic_id

DOCS = Path(__file__).resolve().parents[1] / "docs" / "episode_format.md"


def test_new_classes_are_appended_so_old_ids_stay():
    assert OBJECT_CLASSES[:7] == ("car", "van", "truck", "bus", "motorcycle", "bicycle", "drone")
    assert OBJECT_CLASSES[7:] == ("pedestrian", "static_obstacle")
    assert semantic_id("drone") == 16 and semantic_id("pedestrian") == 17 and semantic_id("static_obstacle") == 18
    assert set(OBJECT_CLASSES) <= set(SEMANTIC_CLASSES) and set(SEMANTIC_COLOURS) == set(SEMANTIC_CLASSES)
    assert len(set(SEMANTIC_COLOURS.values())) == len(SEMANTIC_COLOURS)  # every class tells apart on a plot


def test_docs_table_matches_the_code():
    rows = re.findall(r"^\| (\d+) \| `([a-z_]+)`[^|]*\| \((\d+), (\d+), (\d+)\) \| (yes)? *\|$", DOCS.read_text(), re.M)
    assert [(int(i), n) for i, n, *_ in rows] == list(enumerate(SEMANTIC_CLASSES))
    assert {n: tuple(map(int, c)) for _, n, *c, _ in rows} == SEMANTIC_COLOURS
    assert [n for _, n, *_, obj in rows if obj] == list(OBJECT_CLASSES)
    assert class_table()["object_classes"] == list(OBJECT_CLASSES)


def test_every_object_class_has_a_mesh_a_bev_layer_and_a_box_colour():
    from cosim.io.render import BOX_COLOURS
    from sensors.bev import DYNAMIC_LAYERS
    from sensors.meshes import actor_material, template_for

    assert set(BOX_COLOURS) == set(OBJECT_CLASSES) and DYNAMIC_LAYERS == OBJECT_CLASSES
    for cls in OBJECT_CLASSES:
        tpl = template_for(cls)
        assert np.all(np.abs(tpl.vertices) <= 0.5 + 1e-6), cls  # in the unit box, scaled to the label's size
        albedo, _, _ = actor_material(cls, 3, tpl.part)
        assert albedo.shape == (len(tpl.triangles), 3)
