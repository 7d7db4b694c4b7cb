"""Pictures of the shipped incident scenarios for docs/img (docs/events.md): per event kind, a zoomed top
view around the event and the image of the connected vehicle's camera that sees most of it.

    PYTHONPATH=. nice .venv/bin/python benchmarks/event_pictures.py --out docs/img

Runs each ``scenarios/event_<kind>.yaml`` for a few seconds after its event (real SUMO, drones, sensors at
``--image-scale``) into ``--work``, picks the first tick ``--after-s`` after the event became active, and
writes ``event_<kind>_bev.png`` and ``event_<kind>_camera.png``.
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

KINDS = {  # kind: (episode duration [s], seconds after activation to picture)
    "breakdown": (4.0, 1.6),
    "accident": (2.0, 1.0),
    "lane_closure": (3.0, 2.0),
    "road_block": (4.0, 1.0),
    "jaywalk": (4.0, 2.4),
    "cut_in": (4.0, 1.6),
}


def _focus(event: dict, objects: dict[int, dict]) -> np.ndarray:
    """Map x, y the pictures centre on: the event's zone, else its actors."""
    if event.get("zone_m"):
        return np.mean(np.array(event["zone_m"], float), axis=0)
    ids = event.get("vehicle_track_ids", []) + event.get("pedestrian_track_ids", [])
    return np.mean([objects[i]["center_m"][:2] for i in ids if i in objects], axis=0)


def picture(kind: str, work: Path, out: Path, image_scale: float) -> None:
    duration, after_s = KINDS[kind]
    ep_dir = work / kind
    if not any(ep_dir.glob("*.mcap")):
        cmd = [sys.executable, "-m", "cosim.cli", "run", f"scenarios/event_{kind}.yaml", "--duration", str(duration),
               "--out", str(ep_dir), "--set", f"sensors.image_scale={image_scale}", "--set", "agents.rsus.count=0",
               "-q"]
        subprocess.run(cmd, check=True)
    path = next(ep_dir.glob("*.mcap"))
    with open_episode(path) as ep:
        layout = layout_polygons(ep)
        chosen = None
        for tick in ep.ticks():
            (event,) = json.loads(tick.raw("/events").data)["events"]
            start = event.get("active_from_ns")
            if start is not None and tick.t_ns >= start + after_s * 1e9:
                chosen = tick.index
                break
        if chosen is None:
            chosen = ep.n_ticks - 1
        tick = ep.tick(chosen)
        (event,) = json.loads(tick.raw("/events").data)["events"]
        objects = {o["track_id"]: o for o in json.loads(tick.raw("/labels/objects").data)["objects"]}
        focus = _focus(event, objects)
        bev_plot(ep, tick, out / f"event_{kind}_bev.png", dpi=70, layout=layout,
                 window_m=(float(focus[0]), float(focus[1]), 30.0))
        wanted = set(event.get("vehicle_track_ids", []) + event.get("pedestrian_track_ids", [])
                     + event.get("obstacle_track_ids", []))
        best, best_px = ("vehicle_0", "front"), -1
        for agent in ep.agents:
            for cam in ep.cameras(agent):
                topic = f"/{agent}/{cam}/instance"
                if topic not in tick:
                    continue
                px = int(np.isin(tick[topic].array, list(wanted)).sum())
                if px > best_px:
                    best, best_px = (agent, cam), px
        rgb = camera_with_boxes(ep, tick, *best)
        Image.fromarray(rgb).save(out / f"event_{kind}_camera.png", optimize=True)
        print(f"{kind}: tick {chosen}, state {event['state']}, camera {best[0]}/{best[1]} ({best_px} px of the event)")


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
