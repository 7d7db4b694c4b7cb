"""``cosim render``: contact sheets and BEV plots, and the geometry behind the BEV."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from cosim.cli import main
from cosim.io import open_episode
from cosim.io.decode import Image as DecodedImage
from cosim.io.render import bev_points, colourise_semantic, layout_polygons, semantic_palette
from cosim.io.synthetic import write_synthetic_episode
from cosim.tools import parse_ticks


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    return write_synthetic_episode(tmp_path_factory.mktemp("render") / "ep.mcap", ticks=6)


def test_render_writes_a_contact_sheet_per_agent_and_a_bev_per_tick(episode, tmp_path, capsys):
    assert main(["render", str(episode), "--out", str(tmp_path), "--ticks", "0,-1", "--dpi", "50"]) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(
        [f"contact_{a}_t{k:04d}.png" for a in ("vehicle_0", "rsu_0", "drone_0") for k in (0, 5)]
        + ["bev_t0000.png", "bev_t0005.png"]
    )
    with Image.open(tmp_path / "contact_vehicle_0_t0005.png") as im:
        w, h = im.size
    with Image.open(tmp_path / "contact_drone_0_t0005.png") as im:
        assert im.size[0] == w and im.size[1] < h  # one camera row instead of two
    assert all(p.stat().st_size < 400_000 for p in tmp_path.iterdir())
    assert main(["render", str(episode), "--out", str(tmp_path), "--ticks", "99"]) == 2
    assert main(["render", str(episode), "--out", str(tmp_path), "--agents", "rsu_7"]) == 2


def test_bev_points_are_moved_into_map_through_tf(episode):
    with open_episode(episode) as ep:
        tick = ep.tick(3)
        xyz, cls = bev_points(ep, tick)
        agents = {a["agent_id"]: np.array(a["position_m"]) for a in tick.labels.agents}
    assert xyz.shape == (3 * 64, 3) and cls is not None and (cls == 1).all()
    for i, agent in enumerate(["vehicle_0", "rsu_0", "drone_0"]):
        ring = xyz[64 * i : 64 * (i + 1)]
        # the synthetic cloud is a 10 m ring 1.9 m below a LiDAR mounted 1.9 m above base_link
        assert np.hypot(*(ring[:, :2] - agents[agent][:2]).T) == pytest.approx(np.full(64, 10.0), abs=0.003)
        assert ring[:, 2] == pytest.approx(np.full(64, agents[agent][2]), abs=0.003)


def test_the_static_layout_comes_from_the_world_attachment(episode):
    with open_episode(episode) as ep:
        layout = layout_polygons(ep)
    assert [c for c, _ in layout] == ["road"]
    assert layout[0][1] == pytest.approx(np.array([[-10, -4], [200, -4], [200, 4], [-10, 4]]))


def test_colour_helpers():
    pal = semantic_palette()
    assert tuple(pal[1]) == (128, 64, 128)  # road
    assert colourise_semantic(np.array([[1, 0]]), pal).shape == (1, 2, 3)

    d = DecodedImage(0, "f", "16UC1", np.array([[0, 1500, 65535]], np.uint16)).depth_m
    assert np.isnan(d[0, 0]) and d[0, 1] == pytest.approx(1.5) and np.isnan(d[0, 2])
    d = DecodedImage(0, "f", "32FC1", np.array([[0.0, 80.25, np.inf]], np.float32)).depth_m
    assert np.isnan(d[0, 0]) and d[0, 1] == pytest.approx(80.25) and np.isnan(d[0, 2])


def test_tick_selection():
    assert parse_ticks(None, 10) == [0, 5, 9]
    assert parse_ticks("0:10:4,-1", 10) == [0, 4, 8, 9]
