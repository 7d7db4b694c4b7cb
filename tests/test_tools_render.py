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
        # the synthetic cloud is a 10 m ring 1.9 m below a LiDAR mounted 1.9 m above base_link (stored on 1/128 m)
        assert np.hypot(*(ring[:, :2] - agents[agent][:2]).T) == pytest.approx(np.full(64, 10.0), abs=0.006)
        assert ring[:, 2] == pytest.approx(np.full(64, agents[agent][2]), abs=0.006)


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


def _fill_instance_with_every_track(tick, topic, msg):
    """Edit for the synthetic episode: vehicle_0's rear instance image holds tracks 1, 2, 3 in bands of rows."""
    if topic != "/vehicle_0/rear/instance":
        return msg
    ids = (np.arange(msg.height * msg.width, dtype=np.int32).reshape(msg.height, msg.width) // msg.width) % 3 + 1
    msg.data = ids.tobytes()
    return msg


def test_box_edges_are_drawn_where_the_projected_corners_are(tmp_path):
    from cosim.io.render import BOX_COLOURS, camera_with_boxes

    path = write_synthetic_episode(
        tmp_path / "ep.mcap", ticks=2, width=320, height=240, edit=_fill_instance_with_every_track
    )
    with open_episode(path) as ep:
        tick = ep.tick(1)
        raw = tick.image("vehicle_0", "rear").array
        drawn = camera_with_boxes(ep, tick, "vehicle_0", "rear")
        labels = tick.labels
        optical_from_map = np.linalg.inv(tick.transforms.to_root(tick.image("vehicle_0", "rear").frame_id))
        K = tick.calibration("vehicle_0", "rear").K
    truck = labels.classes.index("truck")  # the truck drives 5 m behind vehicle_0: in its rear camera
    assert labels.rotations[truck] == pytest.approx([0, 0, 0, 1])  # axis-aligned: corners by hand
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    corners = labels.centers_m[truck] + signs * labels.sizes_m[truck] / 2
    cam = corners @ optical_from_map[:3, :3].T + optical_from_map[:3, 3]
    assert (cam[:, 2] > 1).all()  # every corner in front of the camera
    uv = cam[:, :2] / cam[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    edges = [(uv[i], uv[j]) for i in range(8) for j in range(i + 1, 8) if np.count_nonzero(signs[i] != signs[j]) == 1]
    assert len(edges) == 12
    is_box = (drawn == BOX_COLOURS["truck"]).all(axis=2)
    on_edges = 0
    for a, b in edges:  # every point along every edge inside the image lies on a box-coloured pixel (+-1 px)
        for f in np.linspace(0.0, 1.0, 41):
            u, v = a + f * (b - a)
            if 0 <= u < 320 and 0 <= v < 240:
                col, row = int(u), int(v)
                assert is_box[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2].any(), (a, b, f)
                on_edges += 1
    assert on_edges > 200
    changed = (drawn != raw).any(axis=2)
    assert (changed == is_box).all()  # nothing else drawn: the drone is behind, vehicle_0 is the ego
    rows, cols = np.nonzero(changed)
    centres = np.stack([cols + 0.5, rows + 0.5], axis=1)
    dist = np.full(len(centres), np.inf)
    for a, b in edges:  # and every drawn pixel touches a projected edge
        t = np.clip((centres - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
        dist = np.minimum(dist, np.hypot(*(centres - (a + t[:, None] * (b - a))).T))
    assert dist.max() <= np.sqrt(0.5) + 1e-9
    assert 0 < changed.mean() < 0.2


def test_only_boxes_the_camera_sees_are_drawn(episode):
    """In the plain synthetic episode the truck is not in the rear camera's instance image: no box drawn."""
    from cosim.io.render import camera_with_boxes

    with open_episode(episode) as ep:
        tick = ep.tick(1)
        assert "truck" in tick.labels.classes
        for agent in ep.agents:
            for cam in ep.cameras(agent):
                assert (camera_with_boxes(ep, tick, agent, cam) == tick.image(agent, cam).array).all()


def test_instance_colours():
    from cosim.classes import OBJECT_CLASSES
    from cosim.io.render import BOX_COLOURS, colourise_instance

    rgb = colourise_instance(np.array([[0, 1, 2, 3, 1]]))
    assert tuple(rgb[0, 0]) == (0, 0, 0)
    assert (rgb[0, 1] == rgb[0, 4]).all() and len({tuple(c) for c in rgb[0, 1:4]}) == 3
    assert (rgb[0, 1:].max(axis=1) > 96).all()
    assert set(BOX_COLOURS) == set(OBJECT_CLASSES)


def test_depth_colours_are_not_dark_at_both_ends_and_span_a_drones_range():
    """A drone's nadir view holds ground 40-60 m away: its colours span that range (not 0 to 60 m), and the map
    runs from bright (near) to dark (far), not dark at both ends as turbo_r did."""
    import itertools

    import matplotlib

    from cosim.io.render import DEPTH_CMAP, depth_limits

    rng = np.random.default_rng(0)
    drone = rng.uniform(40.0, 60.0, (48, 64))
    drone[:4] = np.inf  # no return
    lo, hi = depth_limits(drone)
    assert 40.0 <= lo < 41.0 and 59.0 < hi <= 60.0
    assert depth_limits(np.full((2, 2), np.nan)) == (0.0, 1.0)

    def lightness(rgba) -> float:
        r, g, b = rgba[:3]
        return 0.2126 * r + 0.7152 * g + 0.0722 * b

    cmap = matplotlib.colormaps[DEPTH_CMAP]
    ends = [lightness(cmap(0.0)), lightness(cmap(1.0))]
    assert max(ends) > 0.6 and abs(ends[0] - ends[1]) > 0.5, ends
    values = [lightness(cmap(x)) for x in np.linspace(0, 1, 11)]
    assert all(a >= b for a, b in itertools.pairwise(values)), values  # brighter near, darker far, no dip


def _sheet_edits(tick, topic, msg):
    """vehicle_0's rear instance image holds every track (so the truck's box is drawn there), and every depth
    image has no return in its top quarter."""
    if topic.endswith("/depth"):
        depth = np.frombuffer(msg.data, np.float32).reshape(msg.height, msg.width).copy()
        depth[: msg.height // 4] = np.inf
        msg.data = depth.tobytes()
        return msg
    return _fill_instance_with_every_track(tick, topic, msg)


@pytest.fixture(scope="module")
def sheet_episode(tmp_path_factory):
    return write_synthetic_episode(
        tmp_path_factory.mktemp("sheet") / "ep.mcap", ticks=2, width=320, height=240, edit=_sheet_edits
    )


def test_contact_sheet_panels_hold_the_data(sheet_episode, tmp_path):
    """The panels are the camera data shrunk into the sheet: exact instance and semantic label colours, depth
    in the colour map's colours with white where nothing was hit, box edges in their exact colour."""
    import matplotlib

    from cosim.io.render import (
        BOX_COLOURS,
        DEPTH_CMAP,
        colourise_instance,
        contact_sheet,
        contact_sheet_image,
    )

    with open_episode(sheet_episode) as ep:
        tick = ep.tick(1)
        ids = tick["/vehicle_0/front/instance"].array
        im, boxes = contact_sheet_image(ep, tick, "vehicle_0", dpi=50)  # the camera's 320 px into 200: 1.6 : 1
        assert contact_sheet(ep, tick, "vehicle_0", tmp_path / "sheet.png", dpi=50) == tmp_path / "sheet.png"
    sheet = np.asarray(im)

    def panel(cam, kind):
        x0, y0, x1, y1 = boxes[cam, kind]
        return sheet[y0:y1, x0:x1]

    def colours(a):
        return {tuple(int(v) for v in c) for c in np.unique(a.reshape(-1, 3), axis=0)}

    assert set(boxes) == {(c, k) for c in ("front", "rear") for k in ("image", "depth", "semantic", "instance",
                                                                      "depth_bar")}
    assert panel("front", "image").shape == (150, 200, 3)  # panel width 4 in x 50 dpi, the camera's aspect ratio

    # labels are picked, not averaged: only exact label colours, even where a region's edge falls inside a pixel
    track = int(ids.max())  # the synthetic instance image: one live track in its top-left quarter, else 0
    assert set(np.unique(ids)) == {0, track}
    colour = tuple(int(v) for v in colourise_instance(np.array([[track]]))[0, 0])
    inst = panel("front", "instance")
    assert colours(inst) == {(0, 0, 0), colour}
    is_track = (inst == colour).all(axis=2)
    assert is_track[:36, :49].all() and not is_track[38:].any() and not is_track[:, 51:].any()
    sem = panel("front", "semantic")  # class 0 above, road (1) in the bottom half
    assert colours(sem) == {tuple(int(v) for v in semantic_palette()[i]) for i in (0, 1)}
    assert (sem[:74] == semantic_palette()[0]).all() and (sem[76:] == semantic_palette()[1]).all()

    depth = panel("front", "depth")  # no return in the top quarter: white; below it 12.345 m, the far end
    far = np.array(matplotlib.colormaps[DEPTH_CMAP](1.0, bytes=True)[:3])
    assert (depth[:37] == 255).all() and (depth[38:] == far).all()
    assert (far < depth[37]).all() and (depth[37] < 255).all()  # the row across the edge: an area mean
    bar = panel("front", "depth_bar")
    assert (bar[0] == far).all() and (bar[-1] == matplotlib.colormaps[DEPTH_CMAP](0.0, bytes=True)[:3]).all()

    truck = (panel("rear", "image") == BOX_COLOURS["truck"]).all(axis=2)  # the truck's box, 1 px thick
    assert truck.sum() > 50
    assert not (panel("front", "image") == BOX_COLOURS["truck"]).all(axis=2).any()

    with Image.open(tmp_path / "sheet.png") as png:  # the palette PNG keeps the label colours
        assert png.mode == "P" and png.size == im.size
        written = np.asarray(png.convert("RGB"))
    x0, y0 = boxes["front", "instance"][:2]
    assert (written[y0 : y0 + 36, x0 : x0 + 49] == colour).all()


def test_contact_sheet_width_scales_with_dpi(sheet_episode, tmp_path):
    from cosim.io.render import contact_sheet_image

    widths = {}
    for dpi in (50, 80, 100):
        assert main(["render", str(sheet_episode), "--out", str(tmp_path / str(dpi)), "--ticks", "0",
                     "--agents", "rsu_0", "--dpi", str(dpi)]) == 0
        with Image.open(tmp_path / str(dpi) / "contact_rsu_0_t0000.png") as im:
            widths[dpi] = im.size[0]
        with open_episode(sheet_episode) as ep:
            _, boxes = contact_sheet_image(ep, ep.tick(0), "rsu_0", dpi=dpi)
        x0, _, x1, _ = boxes["front", "instance"]
        assert x1 - x0 == round(4 * dpi)
    assert widths[50] < widths[80] < widths[100]
    for dpi, w in widths.items():
        assert 16 * dpi <= w <= 18 * dpi, widths  # about 16 in of panels plus labels and a colour bar


def _crowd(tick, topic, msg):
    """Every agent of the synthetic episode within 2 m of vehicle_0 in /labels/objects (what the maps draw)."""
    if topic != "/labels/objects":
        return msg
    name, schema, payload = msg
    agents = [dict(a) for a in payload["agents"]]
    x, y = next(a["position_m"][:2] for a in agents if a["agent_id"] == "vehicle_0")
    for n, a in enumerate(agents):
        a["position_m"] = [x + 0.7 * n, y + 0.4 * n, *a["position_m"][2:]]
    return name, schema, {**payload, "agents": agents}


def _no_overlap(boxes) -> bool:
    return not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:])


def test_agent_names_are_stacked_not_overprinted(tmp_path, monkeypatch):
    """Agents within a few metres of each other: their names in the BEV and in the comm map get boxes that do
    not overlap (stacked a line apart, with a leader), each name once; a lone agent keeps its place."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.text import Text

    import cosim.io.render as render
    from cosim.io.comm_report import comm_report

    fig, ax = plt.subplots(figsize=(4, 4))
    ax.set_xlim(0, 500)
    ax.set_ylim(0, 500)
    names = [("vehicle_0", 100.0, 100.0), ("drone_0", 101.0, 100.5), ("rsu_0", 99.5, 101.0), ("drone_1", 400, 400)]
    anns = render.place_agent_labels(ax, names, fontsize=8)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = [Text.get_window_extent(a, renderer) for a in anns]  # the names as drawn (without their leaders)
    assert [a.get_text() for a in anns] == [n for n, _, _ in names] and _no_overlap(boxes)
    assert anns[0].xyann == anns[3].xyann == render.LABEL_OFFSET_PT and anns[1].xyann[1] > anns[0].xyann[1]
    plt.close(fig)

    placed = []
    real = render.place_agent_labels

    def recording(ax, labels, fontsize, zorder=6):
        out = real(ax, labels, fontsize, zorder)
        ax.figure.canvas.draw()
        renderer = ax.figure.canvas.get_renderer()
        placed.append(([a.get_text() for a in out], [Text.get_window_extent(a, renderer) for a in out]))
        return out

    monkeypatch.setattr(render, "place_agent_labels", recording)
    path = write_synthetic_episode(tmp_path / "crowd.mcap", ticks=2, sensors=False, edit=_crowd)
    assert main(["render", str(path), "--out", str(tmp_path / "r"), "--ticks", "0", "--dpi", "50"]) == 0
    comm_report(path, tmp_path / "c", map_tick=0, dpi=50)
    assert len(placed) == 2  # the BEV, then the comm map
    for texts, boxes in placed:
        assert sorted(t.split()[0] for t in texts) == ["drone_0", "rsu_0", "vehicle_0"] and _no_overlap(boxes)
