"""JSBSim flight dynamics for the project's quadrotor (``cosim/data/jsbsim/aircraft/cosim_quad``).

JSBSim integrates the 6-DOF rigid body over a WGS84 Earth with its own gravity, atmosphere and wind;
the lagged rotor thrusts, the rotors' reaction torque and body drag enter through the aircraft's
external reactions. JSBSim works in feet, pounds, geodetic coordinates and NED/FRD frames: this
module converts to and from cosim's map ENU (a local tangent plane at the world's geo origin),
body FLU and SI units, and no other module sees JSBSim's units or frames.
"""

from __future__ import annotations

import math
from importlib import resources

import jsbsim
import numpy as np

from cosim.drones.airframe import G_MPS2, Airframe
from cosim.drones.backends.base import DynamicsBackend, register_backend
from cosim.drones.control import BodyState
from cosim.geometry import FT_TO_M, M_TO_FT
from cosim.world.types import World

N_TO_LBS = 0.224808943  # [lbf / N]
KG_TO_LBS = 2.20462262  # [lb / kg] (weight at standard gravity)
NM_TO_LBSFT = N_TO_LBS * M_TO_FT  # [lbf ft / N m]
AIRCRAFT = "cosim_quad"
MAX_JSBSIM_DT_S = 0.01  # [s] longest JSBSim integration step

_WGS84_A = 6378137.0  # [m] semi-major axis
_WGS84_E2 = 6.69437999014e-3  # first eccentricity squared

#: Body FRD -> body FLU (and back): a half turn about x.
_FLU_FROM_FRD = np.diag([1.0, -1.0, -1.0])


def _geodetic_to_ecef(lat: float, lon: float, h: float) -> np.ndarray:
    """(3,) ECEF [m] of geodetic latitude, longitude [rad] and ellipsoidal height [m] (WGS84)."""
    s, c = math.sin(lat), math.cos(lat)
    n = _WGS84_A / math.sqrt(1.0 - _WGS84_E2 * s * s)
    return np.array([(n + h) * c * math.cos(lon), (n + h) * c * math.sin(lon), (n * (1.0 - _WGS84_E2) + h) * s])


def _ecef_to_geodetic(p: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`_geodetic_to_ecef` (fixed-point iteration, sub-millimetre in 5 rounds)."""
    x, y, z = (float(v) for v in p)
    lon = math.atan2(y, x)
    r = math.hypot(x, y)
    lat = math.atan2(z, r * (1.0 - _WGS84_E2))
    h = 0.0
    for _ in range(6):
        s = math.sin(lat)
        n = _WGS84_A / math.sqrt(1.0 - _WGS84_E2 * s * s)
        h = r / math.cos(lat) - n
        lat = math.atan2(z, r * (1.0 - _WGS84_E2 * n / (n + h)))
    return lat, lon, h


def _ecef_from_ned(lat: float, lon: float) -> np.ndarray:
    """(3, 3) rotation ECEF <- local NED at (lat, lon) [rad]."""
    sl, cl = math.sin(lat), math.cos(lat)
    so, co = math.sin(lon), math.cos(lon)
    return np.array([[-sl * co, -so, -cl * co], [-sl * so, co, -cl * so], [cl, 0.0, -sl]])


def _ned_from_frd(phi: float, theta: float, psi: float) -> np.ndarray:
    """(3, 3) rotation local NED <- body FRD of JSBSim's Euler angles [rad]."""
    cf, sf = math.cos(phi), math.sin(phi)
    ct, st = math.cos(theta), math.sin(theta)
    cp, sp = math.cos(psi), math.sin(psi)
    return np.array(
        [
            [ct * cp, sf * st * cp - cf * sp, cf * st * cp + sf * sp],
            [ct * sp, sf * st * sp + cf * cp, cf * st * sp - sf * cp],
            [-st, sf * ct, cf * ct],
        ]
    )


class LocalFrame:
    """Map ENU (tangent plane at the geo origin) <-> WGS84 geodetic, exact through ECEF."""

    def __init__(self, lat_deg: float, lon_deg: float, alt_m: float):
        self.lat0, self.lon0, self.alt0 = math.radians(lat_deg), math.radians(lon_deg), alt_m
        self.origin_ecef = _geodetic_to_ecef(self.lat0, self.lon0, alt_m)
        ned0 = _ecef_from_ned(self.lat0, self.lon0)
        # ENU <- NED is a fixed permutation; ENU <- ECEF = (ENU <- NED) (NED <- ECEF).
        self.enu_from_ned = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
        self.enu_from_ecef = self.enu_from_ned @ ned0.T

    def to_map(self, lat: float, lon: float, h: float) -> np.ndarray:
        return self.enu_from_ecef @ (_geodetic_to_ecef(lat, lon, h) - self.origin_ecef)

    def to_geodetic(self, p_map: np.ndarray) -> tuple[float, float, float]:
        return _ecef_to_geodetic(self.origin_ecef + self.enu_from_ecef.T @ p_map)

    def map_from_ned(self, lat: float, lon: float) -> np.ndarray:
        """(3, 3) rotation map ENU <- local NED at (lat, lon)."""
        return self.enu_from_ecef @ _ecef_from_ned(lat, lon)


def data_root() -> str:
    """JSBSim root folder shipped with cosim (holds aircraft/cosim_quad)."""
    return str(resources.files("cosim") / "data" / "jsbsim")


@register_backend("jsbsim")
class JSBSimBackend(DynamicsBackend):
    def __init__(self, frame: Airframe, dt_s: float, world: World):
        super().__init__(frame, dt_s, world)
        self.local = LocalFrame(*world.geo_origin)
        jsbsim.FGJSBBase().debug_lvl = 0
        fdm = jsbsim.FGFDMExec(data_root(), None)
        fdm.set_debug_level(0)
        if not fdm.load_model(AIRCRAFT):
            raise RuntimeError(f"JSBSim could not load aircraft {AIRCRAFT!r} from {data_root()}")
        # JSBSim's multistep integrators go unstable on this small airframe beyond ~20 ms steps:
        # integrate in sub-steps of at most MAX_JSBSIM_DT_S, holding the rotor forces.
        self._substeps = max(1, math.ceil(dt_s / MAX_JSBSIM_DT_S - 1e-9))
        fdm.set_dt(dt_s / self._substeps)
        self.fdm = fdm
        self._configure(frame)
        self._ground_alt_m = world.geo_origin[2] + world.layout.ground_z_m

    def _configure(self, f: Airframe) -> None:
        """Rescale the aircraft file's 3.5 kg vehicle to ``f`` (masses, hub locations, drag)."""
        fdm = self.fdm
        core = 0.55 * f.mass_kg
        arm = (f.mass_kg - core) / 4.0
        fdm["inertia/pointmass-weight-lbs[0]"] = core * KG_TO_LBS
        hubs = f.rotor_positions_m()
        for i, (x, y, _) in enumerate(hubs):
            xs, ys = -x * M_TO_FT * 12.0, -y * M_TO_FT * 12.0  # FLU [m] -> structural (aft, right) [in]
            fdm[f"inertia/pointmass-weight-lbs[{i + 1}]"] = arm * KG_TO_LBS
            fdm[f"inertia/pointmass-location-X-inches[{i + 1}]"] = xs
            fdm[f"inertia/pointmass-location-Y-inches[{i + 1}]"] = ys
            fdm[f"external_reactions/rotor{i}/location-x-in"] = xs
            fdm[f"external_reactions/rotor{i}/location-y-in"] = ys
        fdm["cosim/drag-area-ft2"] = f.drag_area_m2 * M_TO_FT * M_TO_FT
        fdm["cosim/drag-linear-lbs_fps"] = f.drag_linear_nspm * N_TO_LBS * FT_TO_M

    def reset(self, position_m: np.ndarray, yaw_rad: float, velocity_mps: np.ndarray | None = None) -> None:
        fdm = self.fdm
        lat, lon, h = self.local.to_geodetic(np.asarray(position_m, dtype=np.float64))
        fdm["ic/lat-geod-rad"] = lat
        fdm["ic/long-gc-rad"] = lon
        fdm["ic/terrain-elevation-ft"] = self._ground_alt_m * M_TO_FT
        fdm["ic/h-sl-ft"] = h * M_TO_FT  # JSBSim measures it along the WGS84 normal (sub-mm from geodetic)
        # Map yaw (ENU, from east) -> true heading (NED, from north, clockwise).
        fdm["ic/psi-true-rad"] = (math.pi / 2.0 - yaw_rad) % (2.0 * math.pi)
        fdm["ic/theta-rad"] = 0.0
        fdm["ic/phi-rad"] = 0.0
        for k in ("ic/u-fps", "ic/v-fps", "ic/w-fps", "ic/p-rad_sec", "ic/q-rad_sec", "ic/r-rad_sec"):
            fdm[k] = 0.0
        if velocity_mps is not None:  # map ENU -> the local NED frame JSBSim takes
            ve, vn, vu = (float(v) for v in velocity_mps)
            fdm["ic/vn-fps"], fdm["ic/ve-fps"], fdm["ic/vd-fps"] = vn * M_TO_FT, ve * M_TO_FT, -vu * M_TO_FT
        self.rotors.thrust_n = np.full(4, self.frame.hover_thrust_n)
        self._push_rotors()
        self._set_wind(np.zeros(3))
        if not fdm.run_ic():
            raise RuntimeError("JSBSim rejected the initial conditions")
        self._specific_force = np.array([0.0, 0.0, G_MPS2])

    def _push_rotors(self) -> None:
        fdm = self.fdm
        for i, t in enumerate(self.rotors.thrust_n):
            fdm[f"external_reactions/rotor{i}/magnitude"] = float(t) * N_TO_LBS
        _, torque_flu = self.rotors.body_wrench()
        fdm["external_reactions/rotor_torque/magnitude-lbsft"] = -float(torque_flu[2]) * NM_TO_LBSFT

    def _set_wind(self, wind_enu: np.ndarray) -> None:
        fdm = self.fdm
        fdm["atmosphere/wind-north-fps"] = float(wind_enu[1]) * M_TO_FT
        fdm["atmosphere/wind-east-fps"] = float(wind_enu[0]) * M_TO_FT
        fdm["atmosphere/wind-down-fps"] = -float(wind_enu[2]) * M_TO_FT

    def step(self, rotor_command_n: np.ndarray, wind_mps: np.ndarray) -> None:
        self.rotors.step(rotor_command_n)
        self._push_rotors()
        self._set_wind(wind_mps)
        for _ in range(self._substeps):
            self.fdm.run()
        fdm = self.fdm
        m_slug = fdm["inertia/mass-slugs"]
        f_frd = np.array([fdm["forces/fbx-total-lbs"], fdm["forces/fby-total-lbs"], fdm["forces/fbz-total-lbs"]])
        self._specific_force = _FLU_FROM_FRD @ (f_frd / m_slug * FT_TO_M)

    def state(self) -> BodyState:
        fdm = self.fdm
        lat, lon = fdm["position/lat-geod-rad"], fdm["position/long-gc-rad"]
        h = fdm["position/geod-alt-ft"] * FT_TO_M
        map_from_ned = self.local.map_from_ned(lat, lon)
        v_ned = np.array([fdm["velocities/v-north-fps"], fdm["velocities/v-east-fps"], fdm["velocities/v-down-fps"]])
        r_ned_frd = _ned_from_frd(fdm["attitude/phi-rad"], fdm["attitude/theta-rad"], fdm["attitude/psi-rad"])
        pqr = np.array([fdm["velocities/p-rad_sec"], fdm["velocities/q-rad_sec"], fdm["velocities/r-rad_sec"]])
        return BodyState(
            position_m=self.local.to_map(lat, lon, h),
            rotation=map_from_ned @ r_ned_frd @ _FLU_FROM_FRD,
            velocity_mps=map_from_ned @ v_ned * FT_TO_M,
            rate_radps=_FLU_FROM_FRD @ pqr,
            specific_force_mps2=self._specific_force.copy(),
        )

    def mass_properties(self) -> tuple[float, tuple[float, float, float]]:
        """JSBSim's view of the vehicle: mass [kg] and principal inertia (FLU) [kg m^2]."""
        fdm = self.fdm
        slug_ft2 = 14.5939029 * FT_TO_M * FT_TO_M
        return (
            fdm["inertia/mass-slugs"] * 14.5939029,
            (
                fdm["inertia/ixx-slugs_ft2"] * slug_ft2,
                fdm["inertia/iyy-slugs_ft2"] * slug_ft2,
                fdm["inertia/izz-slugs_ft2"] * slug_ft2,
            ),
        )

    def close(self) -> None:
        self.fdm = None
