"""Pictures of the shipped incident scenarios for docs/img (docs/events.md): per event kind, a zoomed top
view around the event and the image of the connected vehicle's camera that sees most of it.

    PYTHONPATH=. nice .venv/bin/python benchmarks/event_pictures.py --out docs/img

Runs each ``scenarios/event_<kind>.yaml`` for a few seconds (real SUMO, drones, sensors at ``--image-scale``)
into ``--work``, picks the tick and camera (any agent's) that see most of the event's actors (instance
pixels, not cut by the image's edge) while it is active (for a breakdown: while its hazard lamps are lit), and writes
``event_<kind>_camera.png`` (boxes drawn) and ``event_<kind>_bev.png`` (60 m square around the event).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import numpy as np
from PIL import Image

from cosim.io import open_episode
from cosim.io.render import bev_plot, camera_with_boxes, layout_polygons

KINDS = {"breakdown": 7.0, "accident": 6.0, "lane_closure": 6.0, "road_block": 5.0, "jaywalk": 5.0, "cut_in": 5.0}
HAZARD_PERIOD_NS = 666_666_667  # cosim.traffic.events
MIN_PIXELS = 100  # a camera picture only when some camera saw at least this many pixels of the event


def _focus(event: dict, objects: dict[int, dict]) -> np.ndarray:
    """Map x, y the pictures centre on: the event's actors and obstacles, else its zone."""
    ids = event.get("vehicle_track_ids", []) + event.get("pedestrian_track_ids", []) + event.get(
        "obstacle_track_ids", [])
    points = [objects[i]["center_m"][:2] for i in ids if i in objects]
    return np.mean(points, axis=0) if points else np.mean(np.array(event["zone_m"], float), axis=0)


def _event_pixels(tick, wanted: set[int]) -> tuple[int, tuple[str, str]]:
    best, best_px = ("vehicle_0", "front"), -1
    for topic in tick.topics:
        if topic.endswith("/instance"):
            mask = np.isin(tick[topic].array, list(wanted))
            cols = np.flatnonzero(mask.any(axis=0))
            if len(cols) and (cols[0] == 0 or cols[-1] == mask.shape[1] - 1):
                continue  # cut by the image's edge: another camera (or tick) shows it whole
            px = int(mask.sum())
            if px > best_px:
                _, agent, cam, _ = topic.split("/")
                best, best_px = (agent, cam), px
    return best_px, best


def picture(kind: str, work: Path, out: Path, image_scale: float) -> None:
    ep_dir = work / kind
    if not any(ep_dir.glob("*.mcap")):
        cmd = [sys.executable, "-m", "cosim.cli", "run", f"scenarios/event_{kind}.yaml", "--duration", str(KINDS[kind]),
               "--out", str(ep_dir), "--set", f"sensors.image_scale={image_scale}", "--set", "agents.rsus.count=0",
               "-q"]
        subprocess.run(cmd, check=True)
    path = next(ep_dir.glob("*.mcap"))
    with open_episode(path) as ep:
        layout = layout_polygons(ep)
        best = (-1, 0, ("vehicle_0", "front"))
        for tick in ep.ticks():
            (event,) = json.loads(tick.raw("/events").data)["events"]
            start = event.get("active_from_ns")
            if event["state"] != "active" or (event.get("hazard_lights") and (tick.t_ns - start) % HAZARD_PERIOD_NS
                                                >= HAZARD_PERIOD_NS // 2):
                continue
            wanted = set(event.get("vehicle_track_ids", []) + event.get("pedestrian_track_ids", [])
                         + event.get("obstacle_track_ids", []))
            px, cam = _event_pixels(tick, wanted)
            if px > best[0]:
                best = (px, tick.index, cam)
        px, index, cam = best
        tick = ep.tick(index)
        (event,) = json.loads(tick.raw("/events").data)["events"]
        objects = {o["track_id"]: o for o in json.loads(tick.raw("/labels/objects").data)["objects"]}
        focus = _focus(event, objects)
        bev_plot(ep, tick, out / f"event_{kind}_bev.png", dpi=70, layout=layout,
                 window_m=(float(focus[0]), float(focus[1]), 30.0))
        if px >= MIN_PIXELS:
            Image.fromarray(camera_with_boxes(ep, tick, *cam)).save(out / f"event_{kind}_camera.png", optimize=True)
        print(f"{kind}: tick {index}, camera {cam[0]}/{cam[1]} ({px} px of the event)"
              + ("" if px >= MIN_PIXELS else ": no camera picture, no camera saw the event whole"))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("docs/img"))
    p.add_argument("--work", type=Path, default=Path("/tmp/event_pictures"))
    p.add_argument("--image-scale", type=float, default=0.5)
    p.add_argument("--kinds", nargs="*", default=list(KINDS))
    a = p.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    for kind in a.kinds:
        picture(kind, a.work, a.out, a.image_scale)


if __name__ == "__main__":
    main()
