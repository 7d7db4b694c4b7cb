"""Acceptance flights for the drone stack: hover, patrol and escort on every backend, with metrics
and plots (flown path against the target, error over time).

    python -m benchmarks.drone_report --out docs/img

prints one line per strategy and backend (errors, waypoints, speed relative to real time) and writes
``drone_hover.png``, ``drone_patrol.png`` and ``drone_escort.png``. Inputs come from
:mod:`benchmarks.drone_demo` (no SUMO needed); the scenario defaults give the wind and gusts.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from benchmarks.drone_demo import DEMO_ROUTE, demo_world, synthetic_drive
from cosim.drones.backends import backend_names
from cosim.drones.fleet import DroneFleet
from cosim.protocol import DroneState, EscortTarget
from cosim.scenario.model import AgentsSpec, EscortDrone, HoverDrone, PatrolDrone, Scenario, VehicleAgents
from cosim.world.types import World

log = logging.getLogger(__name__)

HOVER_POINT = (300.0, 300.0)
PATROL_WAYPOINTS = [(100.0, 100.0), (300.0, 100.0), (300.0, 300.0), (200.0, 250.0), (100.0, 300.0)]


@dataclass
class Flight:
    """One drone's flight sampled at the tick rate, with its target and error."""

    backend: str
    t_s: np.ndarray  # (N,)
    position_m: np.ndarray  # (N, 3) map
    target_m: np.ndarray  # (N, 3) what it should be at (hover point, nearest path point, offset point)
    states: list[DroneState]
    cpu_s: float  # process CPU time of the stepping (robust to other load on the machine)
    extra: dict = field(default_factory=dict)

    @property
    def err_h_m(self) -> np.ndarray:
        d = self.position_m[:, :2] - self.target_m[:, :2]
        return np.hypot(d[:, 0], d[:, 1])

    @property
    def err_v_m(self) -> np.ndarray:
        return self.position_m[:, 2] - self.target_m[:, 2]

    @property
    def speedup(self) -> float:
        """Simulated seconds per CPU second of stepping (one drone: real-time factor per drone)."""
        return float(self.t_s[-1]) / self.cpu_s


def rms(x: np.ndarray) -> float:
    return float(math.sqrt(np.mean(np.square(x))))


def run_fleet(sc: Scenario, world: World, seconds: float, targets=None) -> tuple[list[list[DroneState]], float]:
    """Fly a fleet from t=0 for ``seconds``; ``targets(k)`` gives the escort targets sent with tick k.

    Returns the states per tick (index 0: t=0) and the process CPU time of the stepping [s].
    """
    fleet = DroneFleet(sc, world)
    try:
        out = [fleet.step_to(0, 0, targets(0) if targets else {})]
        start = time.process_time()
        for k in range(1, round(seconds * 1e9 / sc.tick_ns) + 1):
            out.append(fleet.step_to(k * sc.tick_ns, k, targets(k) if targets else {}))
        return out, time.process_time() - start
    finally:
        fleet.close()


def _scenario(drones: list, backend: str, seed: int, seconds: float, vehicles: int = 0) -> Scenario:
    return Scenario(
        name="drone-acceptance",
        seed=seed,
        duration_s=seconds,
        agents=AgentsSpec(drones=drones, drone_backend=backend, vehicles=VehicleAgents(count=vehicles)),
    )


def fly_hover(backend: str, seconds: float = 60.0, seed: int = 0) -> Flight:
    world = demo_world()
    sc = _scenario([HoverDrone(point=HOVER_POINT, altitude_m=50.0)], backend, seed, seconds)
    states, cpu = run_fleet(sc, world, seconds)
    pos = np.array([s[0].position_m for s in states])
    target = np.tile([HOVER_POINT[0], HOVER_POINT[1], 50.0], (len(pos), 1))
    t = np.arange(len(pos)) * sc.tick_ns * 1e-9
    return Flight(backend, t, pos, target, [s[0] for s in states], cpu)


def nearest_on_loop(p_xy: np.ndarray, loop_xy: np.ndarray) -> np.ndarray:
    """(2,) the point of the closed polyline ``loop_xy`` (N, 2) nearest to ``p_xy``."""
    a = loop_xy
    b = np.roll(loop_xy, -1, axis=0)
    ab = b - a
    u = np.clip(np.einsum("ij,ij->i", p_xy - a, ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
    q = a + ab * u[:, None]
    return q[np.argmin(np.hypot(*(q - p_xy).T))]


def fly_patrol(backend: str, loops: int = 2, seed: int = 0) -> Flight:
    world = demo_world()
    wps = np.array(PATROL_WAYPOINTS)
    spec = PatrolDrone(waypoints=PATROL_WAYPOINTS, altitude_m=40.0, speed_mps=10.0)
    perimeter = float(np.sum(np.linalg.norm(np.roll(wps, -1, axis=0) - wps, axis=1)))
    seconds = round(loops * perimeter / spec.speed_mps * 1.45 / 0.2) * 0.2
    sc = _scenario([spec], backend, seed, seconds)
    states, cpu = run_fleet(sc, world, seconds)
    pos = np.array([s[0].position_m for s in states])
    target = np.array([[*nearest_on_loop(p[:2], wps), 40.0] for p in pos])
    t = np.arange(len(pos)) * sc.tick_ns * 1e-9
    f = Flight(backend, t, pos, target, [s[0] for s in states], cpu)
    f.extra["waypoints"] = wps
    f.extra["visits"] = waypoint_visits([s.strategy_state for s in f.states], pos, wps)
    return f


def waypoint_visits(labels: list[str], pos: np.ndarray, wps: np.ndarray) -> list[tuple[int, float]]:
    """Each completed leg as (waypoint index, closest horizontal approach [m]), from the per-tick
    ``to_wp_<i>`` labels: a leg toward waypoint i ends when the label moves on."""
    visits = []
    start = 0
    for k in range(1, len(labels) + 1):
        if k == len(labels) or labels[k] != labels[start]:
            if k < len(labels):
                i = int(labels[start].rsplit("_", 1)[1])
                window = pos[start : k + 1, :2] - wps[i]
                visits.append((i, float(np.min(np.hypot(window[:, 0], window[:, 1])))))
            start = k
    return visits


def fly_escort(backend: str, seed: int = 0) -> Flight:
    world = demo_world()
    drive = synthetic_drive(DEMO_ROUTE)
    tick_s = 0.2
    seconds = math.floor(drive.duration_s / tick_s) * tick_s
    spec = EscortDrone(target="vehicle_0", offset_m=(-8.0, 0.0), altitude_m=40.0)
    sc = _scenario([spec], backend, seed, round(seconds, 1), vehicles=1)

    def targets(k: int) -> dict[str, EscortTarget]:
        # The conductor sends the target's state at the PREVIOUS tick (at t=0: at t=0).
        return {"drone_0": drive.target_at(max(k - 1, 0) * tick_s)}

    states, cpu = run_fleet(sc, world, seconds, targets)
    pos = np.array([s[0].position_m for s in states])
    target = []
    for k in range(len(pos)):
        tg = drive.target_at(k * tick_s)
        c, s = math.cos(tg.yaw_rad), math.sin(tg.yaw_rad)
        fx, ly = spec.offset_m
        target.append([tg.center_m[0] + c * fx - s * ly, tg.center_m[1] + s * fx + c * ly, 40.0])
    t = np.arange(len(pos)) * tick_s
    f = Flight(backend, t, pos, np.array(target), [s[0] for s in states], cpu)
    f.extra["car_xy"] = drive.pos
    f.extra["car_speed"] = np.interp(t, drive.t, np.hypot(drive.vel[:, 0], drive.vel[:, 1]))
    return f


# ------------------------------------------------------------------------------------------ plots

_COLORS = {"jsbsim": "tab:blue", "pybullet": "tab:orange"}


def _draw_world(ax, world: World) -> None:
    from matplotlib.patches import Polygon

    for p in world.layout.prisms:
        if p.cls != "building":
            continue
        ax.add_patch(Polygon(p.footprint, closed=True, color="0.8", zorder=0))
        cx = float(np.mean([q[0] for q in p.footprint]))
        cy = float(np.mean([q[1] for q in p.footprint]))
        ax.text(cx, cy, f"{p.z1_m:.0f} m", ha="center", va="center", fontsize=7, color="0.4", clip_on=True)


def plot_flights(kind: str, flights: list[Flight], world: World, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_map, ax_err) = plt.subplots(2, 1, figsize=(8.5, 9), gridspec_kw={"height_ratios": [3, 2]})
    f0 = flights[0]
    if kind == "hover":
        ax_map.plot(0.0, 0.0, "k+", ms=14, label="hover point")
        ax_map.add_patch(plt.Circle((0.0, 0.0), 0.5, fill=False, color="k", ls="--", lw=0.8))
        for f in flights:
            d = f.position_m[:, :2] - f.target_m[:, :2]
            ax_map.plot(d[:, 0], d[:, 1], color=_COLORS.get(f.backend), lw=0.8, label=f.backend)
        ax_map.set_xlim(-0.6, 0.6)
        ax_map.set_ylim(-0.6, 0.6)
        ax_map.set_title("hover at 50 m, wind 3 m/s + gusts 1.5 m/s: horizontal offset (dashed: 0.5 m)")
    elif kind == "patrol":
        _draw_world(ax_map, world)
        w = np.vstack([f0.extra["waypoints"], f0.extra["waypoints"][:1]])
        ax_map.plot(w[:, 0], w[:, 1], "k--", lw=1, label="waypoint loop")
        for i, (x, y) in enumerate(f0.extra["waypoints"]):
            ax_map.add_patch(plt.Circle((x, y), 2.0, fill=False, color="k", lw=0.8))
            ax_map.annotate(f"wp{i}", (x, y), textcoords="offset points", xytext=(6, 6), fontsize=8)
        for f in flights:
            ax_map.plot(f.position_m[:, 0], f.position_m[:, 1], color=_COLORS.get(f.backend), lw=1, label=f.backend)
        ax_map.set_title("patrol at 10 m/s, 2 loops (circles: 2 m reach radius)")
    else:
        _draw_world(ax_map, world)
        car = f0.extra["car_xy"]
        ax_map.plot(car[:, 0], car[:, 1], color="0.3", lw=1, label="escorted car")
        ax_map.plot(f0.target_m[:, 0], f0.target_m[:, 1], "k--", lw=1, label="offset point (8 m behind)")
        for f in flights:
            ax_map.plot(f.position_m[:, 0], f.position_m[:, 1], color=_COLORS.get(f.backend), lw=1, label=f.backend)
        ax_map.set_title("escort: car up to 14 m/s with 90-degree turns; target state arrives one tick late")
    ax_map.set_aspect("equal")
    ax_map.set_xlabel("east offset [m]" if kind == "hover" else "map x [m]")
    ax_map.set_ylabel("north offset [m]" if kind == "hover" else "map y [m]")
    ax_map.legend(loc="best", fontsize=8)

    for f in flights:
        c = _COLORS.get(f.backend)
        label = {"hover": "horizontal", "patrol": "cross-track", "escort": "to offset point"}[kind]
        ax_err.plot(f.t_s, f.err_h_m, color=c, lw=1, label=f"{f.backend} {label} (RMS {rms(f.err_h_m):.2f} m)")
        if kind == "hover":
            ax_err.plot(
                f.t_s,
                np.abs(f.err_v_m),
                color=c,
                lw=1,
                ls=":",
                label=f"{f.backend} vertical (RMS {rms(f.err_v_m):.2f} m)",
            )
    if kind == "escort":
        ax2 = ax_err.twinx()
        ax2.plot(f0.t_s, f0.extra["car_speed"], color="0.6", lw=0.8)
        ax2.set_ylabel("car speed [m/s]", color="0.5")
    ax_err.set_xlabel("time [s]")
    ax_err.set_ylabel("error [m]")
    ax_err.grid(alpha=0.3)
    ax_err.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=None, help="folder for drone_<strategy>.png (default: no plots)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    world = demo_world()
    backends = backend_names()
    results = {
        "hover": [fly_hover(b, seed=args.seed) for b in backends],
        "patrol": [fly_patrol(b, seed=args.seed) for b in backends],
        "escort": [fly_escort(b, seed=args.seed) for b in backends],
    }
    for kind, flights in results.items():
        for f in flights:
            line = f"{kind:7s} {f.backend:9s} "
            if kind == "hover":
                line += f"horizontal RMS {rms(f.err_h_m):.3f} m, vertical RMS {rms(f.err_v_m):.3f} m"
            elif kind == "patrol":
                visits = f.extra["visits"]
                order = [i for i, _ in visits]
                worst = max(d for _, d in visits)
                line += (
                    f"cross-track RMS {rms(f.err_h_m):.3f} m, legs {len(visits)} in order "
                    f"{order}, closest approach worst {worst:.2f} m"
                )
            else:
                line += f"offset-point RMS {rms(f.err_h_m):.3f} m, max {f.err_h_m.max():.2f} m"
            line += f", {f.speedup:.0f}x real time (CPU)"
            print(line)
        if args.out:
            plot_flights(kind, flights, world, f"{args.out}/drone_{kind}.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
