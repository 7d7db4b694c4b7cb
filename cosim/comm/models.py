"""Path-loss models of the link model, a registry by name (:data:`LINK_MODELS`, docs/comm.md).

A model is a function of the geometry of P unordered pairs (:class:`PairGeometry`) returning their LOS
and NLOS path loss, shadow fading std and decorrelation distances (:class:`PathLoss`); the link model
picks the LOS or NLOS value per pair from the line of sight and adds the NLOSv blockage. The name is what
``/comm/links`` records per link (``model``). The built-in ones follow 3GPP (formulas in
:mod:`cosim.comm.channel`); which one a link uses by default: :func:`cosim.comm.links.pair_channels`,
``comm.link_models`` in a scenario overrides it per link type.

A new model is one module::

    from cosim.comm.models import LINK_MODELS, PairGeometry, PathLoss

    @LINK_MODELS.register("my_model")
    def my_model(g: PairGeometry) -> PathLoss: ...

imported before the episode runs, and ``comm: {link_models: {vehicle-vehicle: my_model}}`` in the scenario.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cosim.comm import channel as ch
from cosim.registry import Registry


@dataclass(frozen=True)
class PairGeometry:
    """What a model sees of P unordered pairs; every array (P,).

    ``h_bs_m``, ``h_ut_m``: the higher and the lower antenna above ground; ``drone_h_m``: the (lower)
    drone end's height above ground, at least 1 m (100 m on pairs without a drone end: those rows are not
    used by the aerial models); ``air_ground``: the episode's TR 36.777 model (``umi_av``, ``uma_av``,
    ``rma_av``)."""

    d3d_m: np.ndarray
    d2d_m: np.ndarray
    h_bs_m: np.ndarray
    h_ut_m: np.ndarray
    drone_h_m: np.ndarray
    fc_ghz: float
    air_ground: str


@dataclass(frozen=True)
class PathLoss:
    """Path loss [dB] in LOS and NLOS, shadow fading std [dB] in each (a number or (P,)), and the fading
    decorrelation distance [m] in (LOS, NLOS)."""

    los_db: np.ndarray
    nlos_db: np.ndarray
    sigma_los_db: float | np.ndarray
    sigma_nlos_db: float | np.ndarray
    decorrelation_m: tuple[float, float]


LinkModelFn = Callable[[PairGeometry], PathLoss]

#: Path-loss models by name: a duplicate name is an error, an unknown one lists the known ones.
LINK_MODELS: Registry[LinkModelFn] = Registry("link model")


@LINK_MODELS.register("tr37885_urban")
def tr37885_urban(g: PairGeometry) -> PathLoss:
    """Vehicle-vehicle, TR 37.885 Table 6.2.1-1, urban."""
    return PathLoss(ch.v2v_urban_los_db(g.d3d_m, g.fc_ghz), ch.v2v_urban_nlos_db(g.d3d_m, g.fc_ghz), 3.0, 4.0,
                    ch.DECORRELATION_M["v2v_urban"])


@LINK_MODELS.register("tr37885_highway")
def tr37885_highway(g: PairGeometry) -> PathLoss:
    """Vehicle-vehicle, TR 37.885 Table 6.2.1-1, highway (NLOS: the urban formula, as the table says)."""
    return PathLoss(ch.v2v_highway_los_db(g.d3d_m, g.fc_ghz), ch.v2v_urban_nlos_db(g.d3d_m, g.fc_ghz), 3.0, 4.0,
                    ch.DECORRELATION_M["v2v_highway"])


@LINK_MODELS.register("tr38901_umi_sc")
def tr38901_umi_sc(g: PairGeometry) -> PathLoss:
    """TR 38.901 UMi-Street Canyon (Table 7.4.1-1), the higher end as "BS"."""
    return PathLoss(ch.umi_sc_los_db(g.d3d_m, g.d2d_m, g.h_bs_m, g.h_ut_m, g.fc_ghz),
                    ch.umi_sc_nlos_db(g.d3d_m, g.d2d_m, g.h_bs_m, g.h_ut_m, g.fc_ghz), 4.0, 7.82,
                    ch.DECORRELATION_M["umi_sc"])


def _air_ground(name: str) -> LinkModelFn:
    los, nlos = {"umi_av": (ch.umi_av_los_db, ch.umi_av_nlos_db), "uma_av": (ch.uma_av_los_db, ch.uma_av_nlos_db),
                 "rma_av": (ch.rma_av_los_db, ch.rma_av_nlos_db)}[name]

    def model(g: PairGeometry) -> PathLoss:
        h = g.drone_h_m
        return PathLoss(los(g.d3d_m, h, g.fc_ghz), nlos(g.d3d_m, h, g.fc_ghz), ch.av_shadow_std_db(name, True, h),
                        ch.av_shadow_std_db(name, False, h), ch.DECORRELATION_M[name])

    model.__doc__ = f"Ground-air, TR 36.777 Table B-2, {name} by the drone's height."
    return model


for _name in ("umi_av", "uma_av", "rma_av"):
    LINK_MODELS.add(f"tr36777_{_name}", _air_ground(_name))


@LINK_MODELS.register("free_space")
def free_space(g: PairGeometry) -> PathLoss:
    """Drone-drone: free space in LOS (TR 36.777 PL_FS); blocked: the episode's air-ground NLOS formula at the
    lower drone's height."""
    aerial = LINK_MODELS.get(f"tr36777_{g.air_ground}")(g)
    return PathLoss(ch.free_space_db(g.d3d_m, g.fc_ghz), aerial.nlos_db, aerial.sigma_los_db, aerial.sigma_nlos_db,
                    ch.DECORRELATION_M["free_space"])
