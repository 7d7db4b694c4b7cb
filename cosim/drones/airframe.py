"""Physical parameters of the project's multirotor: a LiDAR-carrying X-quadrotor of a few kilograms.

Everything scales from the take-off mass so that both dynamics backends (and the JSBSim aircraft
file under ``cosim/data/jsbsim``) describe the same vehicle. Frames: body FLU, origin at the centre
of gravity. Rotor ``i`` sits at ``ROTOR_DIRS[i] * arm_m`` and spins with ``ROTOR_SPIN[i]``
(+1 = counter-clockwise seen from above, which pushes the body clockwise: reaction torque -z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

G_MPS2 = 9.80665  # [m/s^2] standard gravity
RHO_KGPM3 = 1.225  # [kg/m^3] sea-level air density (ISA)

#: Unit directions of the 4 rotors in the body x/y plane: front-left, back-left, back-right, front-right.
ROTOR_DIRS = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]]) / math.sqrt(2.0)
#: Spin direction of each rotor (+1 counter-clockwise seen from above).
ROTOR_SPIN = np.array([1.0, -1.0, 1.0, -1.0])

#: Share of the mass carried by the centre body (battery, LiDAR, computer) vs the 4 arms (motor, prop, ESC).
CORE_MASS_SHARE = 0.55
CORE_RADIUS_M = 0.12  # [m] the centre body as a solid ball (JSBSim pointmass form "ball")


@dataclass(frozen=True, slots=True)
class Airframe:
    """A quadrotor's physical parameters (SI, body FLU)."""

    mass_kg: float
    arm_m: float  # [m] rotor axis to centre of gravity
    inertia_kgm2: tuple[float, float, float]  # [kg m^2] principal Ixx, Iyy, Izz (FLU)
    rotor_max_thrust_n: float  # [N] per rotor
    rotor_tau_s: float  # [s] first-order motor/rotor thrust lag
    rotor_torque_m: float  # [m] reaction torque per newton of thrust (k_q / k_t)
    rotor_diameter_m: float
    drag_area_m2: float  # [m^2] Cd * A of the body (quadratic drag)
    drag_linear_nspm: float  # [N s/m] rotor (blade-flapping / induced) drag, linear in air speed
    hover_power_share: float  # figure of merit * motor+ESC efficiency
    avionics_power_w: float  # [W] LiDAR, computer, radio

    @property
    def hover_thrust_n(self) -> float:
        """[N] per-rotor thrust that balances the weight."""
        return self.mass_kg * G_MPS2 / 4.0

    @property
    def half_extents_m(self) -> tuple[float, float, float]:
        """Collision box of the airframe [m] (body FLU): arms plus propeller discs, and a flat body."""
        half = self.arm_m / math.sqrt(2.0) + 0.5 * self.rotor_diameter_m
        return (half, half, 0.3 * self.arm_m)

    def rotor_positions_m(self) -> np.ndarray:
        """(4, 3) float64 rotor hub positions in body FLU [m]."""
        xy = ROTOR_DIRS * self.arm_m
        return np.column_stack([xy, np.zeros(4)])


def airframe_for_mass(mass_kg: float) -> Airframe:
    """The project's quadrotor scaled to ``mass_kg`` (3.5 kg: a ~650 mm frame with 15-inch props).

    Lengths scale with mass^(1/3); thrust-to-weight stays 2.2.
    """
    s = (mass_kg / 3.5) ** (1.0 / 3.0)
    arm = 0.32 * s
    core = CORE_MASS_SHARE * mass_kg
    motor = (1.0 - CORE_MASS_SHARE) * mass_kg / 4.0
    r_core = CORE_RADIUS_M * s
    i_core = 0.4 * core * r_core * r_core
    # Each motor lies at (+-a/sqrt2, +-a/sqrt2): sum m y^2 = 4 m a^2 / 2.
    i_xy = i_core + 2.0 * motor * arm * arm
    i_z = i_core + 4.0 * motor * arm * arm
    return Airframe(
        mass_kg=mass_kg,
        arm_m=arm,
        inertia_kgm2=(i_xy, i_xy, i_z),
        rotor_max_thrust_n=2.2 * mass_kg * G_MPS2 / 4.0,
        rotor_tau_s=0.04,
        rotor_torque_m=0.016 * s,
        rotor_diameter_m=0.38 * s,
        drag_area_m2=0.06 * s * s,
        drag_linear_nspm=0.06 * mass_kg,
        hover_power_share=0.65 * 0.8,
        avionics_power_w=30.0,
    )


def rotor_power_w(thrust_n: np.ndarray, frame: Airframe, rho_kgpm3: float = RHO_KGPM3) -> float:
    """Electrical power [W] drawn by the rotors at thrusts ``thrust_n`` (4,) [N], plus avionics.

    Momentum theory: ideal induced power T^1.5 / sqrt(2 rho A), divided by figure of merit times
    motor/ESC efficiency.
    """
    area = math.pi * (0.5 * frame.rotor_diameter_m) ** 2
    t = np.maximum(thrust_n, 0.0)
    ideal = float(np.sum(t * np.sqrt(t))) / math.sqrt(2.0 * rho_kgpm3 * area)
    return ideal / frame.hover_power_share + frame.avionics_power_w


@dataclass(slots=True)
class RotorBank:
    """First-order motor lag on the 4 rotor thrusts, exact discretisation at a fixed step.

    ``thrust_n`` (4,) [N] is the delivered thrust; ``step`` moves it toward the command.
    """

    frame: Airframe
    dt_s: float
    thrust_n: np.ndarray
    _hubs: np.ndarray = field(init=False)
    _alpha: float = field(init=False)

    def __post_init__(self) -> None:
        self._hubs = self.frame.rotor_positions_m()
        self._alpha = 1.0 - math.exp(-self.dt_s / self.frame.rotor_tau_s)

    @classmethod
    def hovering(cls, frame: Airframe, dt_s: float) -> RotorBank:
        return cls(frame, dt_s, np.full(4, frame.hover_thrust_n))

    def step(self, command_n: np.ndarray) -> np.ndarray:
        """Advance one step toward ``command_n`` (4,) [N] (clipped to [0, max]); returns the thrusts."""
        cmd = np.clip(command_n, 0.0, self.frame.rotor_max_thrust_n)
        self.thrust_n = self.thrust_n + self._alpha * (cmd - self.thrust_n)
        return self.thrust_n

    def body_wrench(self) -> tuple[np.ndarray, np.ndarray]:
        """Total rotor force and torque about the CG in body FLU: ((3,) [N], (3,) [N m]).

        Each rotor pushes along body +z; its reaction (drag) torque is -spin * k_q * T about +z.
        """
        t = self.thrust_n
        pos = self._hubs
        force = np.array([0.0, 0.0, float(np.sum(t))])
        # r x (0, 0, T) = (y T, -x T, 0)
        torque = np.array(
            [
                float(np.dot(pos[:, 1], t)),
                -float(np.dot(pos[:, 0], t)),
                -float(np.dot(ROTOR_SPIN, t)) * self.frame.rotor_torque_m,
            ]
        )
        return force, torque
