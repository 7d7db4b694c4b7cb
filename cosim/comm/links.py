"""The link model: every ordered pair of connected agents at one tick, from geometry to delay.

:func:`compute_links` is a pure function of the snapshot, the static scene, the configuration
(:class:`cosim.scenario.model.CommSpec`), the previous tick's fading state and a generator; it
returns the tick's :class:`~cosim.comm.message.LinkSet` and the next fading state.
:class:`LinkModel` carries the state from tick to tick for the runner. Per link:

1. geometry: antennas at the agents' base_link plus ``<kind>_antenna_z_m`` along map z; 3D distance;
2. line of sight through the static world and the other actors (:mod:`cosim.comm.los`);
3. the channel model by link type (:mod:`cosim.comm.models`, a registry of path-loss models by name, formulas
   in :mod:`cosim.comm.channel`; ``comm.link_models`` picks another registered model per link type):

   - vehicle-vehicle: TR 37.885 Table 6.2.1-1, urban or highway (``comm.environment``); NLOSv adds
     the section 6.2.1 vehicle blockage loss to the LOS loss;
   - vehicle-RSU and RSU-RSU: TR 38.901 UMi-Street Canyon (Table 7.4.1-1), the model TR 37.885
     names for vehicle-RSU links, RSU as "BS";
   - a drone end: TR 36.777 Table B-2 (``comm.air_ground_model``: UMi-AV in urban settings,
     RMa-AV on highways by default), by the drone's height above ground, when the drone is above
     the table's lowest height (22.5 m; RMa-AV 10 m); below it, the terrestrial UMi-Street Canyon
     with the drone as "BS", as the table prescribes;
   - drone-drone: free space when in LOS (TR 36.777 Table B-2's PL_FS); when blocked, the
     air-to-ground NLOS formula at the lower drone's height;
4. shadow fading: a unit Gaussian per unordered pair, correlated over the distance both ends moved
   since the last tick (Gudmundson: ``z_k = rho z_(k-1) + sqrt(1 - rho^2) n_k``,
   ``rho = exp(-dx / d_corr)``, ``d_corr`` from the model's table), times the model's std for
   the link's current state (:data:`cosim.comm.channel.DECORRELATION_M`); the same value both ways;
5. link budget, SNR, PER, rates and delay (:mod:`cosim.comm.phy`); the message is delivered within
   the tick with probability ``1 - PER`` when its delay fits in one tick, else 0.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from itertools import combinations
from typing import Any

import numpy as np

from cosim.comm import channel as ch
from cosim.comm import phy
from cosim.comm.los import LOS, LOS_STATES, NLOS, NLOSV, LinkScene, line_of_sight
from cosim.comm.message import LINK_ARRAY_SCHEMA, LINK_TYPES, SCHEMA_NAME, TOPIC, LinkSet, links_payload
from cosim.comm.models import LINK_MODELS, PairGeometry
from cosim.errors import InputError
from cosim.snapshot import AgentState, WorldSnapshot

#: Scenario map kinds that are TR 37.885's "highway" setting; every other kind is "urban".
HIGHWAY_MAP_KINDS = frozenset({"highway", "rural"})
#: Random stream of the shadow fading, derived from the scenario seed (see cosim/runner.py).
COMM_STREAM = 0xC0
_KIND_ORDER = {"vehicle": 0, "rsu": 1, "drone": 2}


def setting_of(spec: Any, map_kind: str) -> str:
    """TR 37.885 setting (``urban`` or ``highway``) of a scenario's comm spec and map kind."""
    if spec.environment != "auto":
        return spec.environment
    return "highway" if map_kind in HIGHWAY_MAP_KINDS else "urban"


def air_ground_model_of(spec: Any, setting: str) -> str:
    """TR 36.777 model of the links with a drone end (``umi_av``, ``uma_av`` or ``rma_av``)."""
    if spec.air_ground_model != "auto":
        return spec.air_ground_model
    return "rma_av" if setting == "highway" else "umi_av"


def link_type(kind_a: str, kind_b: str) -> str:
    """``vehicle-vehicle``, ``vehicle-rsu``, ``vehicle-drone``, ``rsu-rsu``, ``rsu-drone`` or ``drone-drone``."""
    a, b = sorted((kind_a, kind_b), key=_KIND_ORDER.__getitem__)
    return f"{a}-{b}"


@dataclass(frozen=True)
class FadingState:
    """Shadow fading carried from one tick to the next: the agents (in snapshot order), each
    unordered pair's unit Gaussian ``z`` (P,) (pairs in :func:`itertools.combinations` order) and
    the antenna positions (n, 3) [m] it was drawn at."""

    agent_ids: tuple[str, ...]
    z: np.ndarray
    antennas_m: np.ndarray


@dataclass(frozen=True)
class PairChannel:
    """Path loss [dB], shadow fading std [dB], decorrelation distance [m] and model name per pair."""

    path_loss_db: np.ndarray
    sigma_db: np.ndarray
    decorrelation_m: np.ndarray
    model: tuple[str, ...]


def antenna_positions(agents: tuple[AgentState, ...], spec: Any) -> np.ndarray:
    """(n, 3) antenna positions [m] in map: base_link + the kind's antenna height along map z."""
    lift = {"vehicle": spec.vehicle_antenna_z_m, "rsu": spec.rsu_antenna_z_m, "drone": spec.drone_antenna_z_m}
    pos = np.array([a.position_m for a in agents], np.float64).reshape(-1, 3)
    return pos + np.array([[0.0, 0.0, lift[a.kind]] for a in agents]).reshape(-1, 3)


def pair_channels(types: list[str], state: np.ndarray, d3d_m: np.ndarray, d2d_m: np.ndarray,
                  h_a_m: np.ndarray, h_b_m: np.ndarray, drone_h_m: np.ndarray, blocker_m: np.ndarray,
                  setting: str, ag_model: str, fc_ghz: float,
                  overrides: Mapping[str, str] | None = None) -> PairChannel:
    """Path loss and fading parameters of P unordered pairs (see the module docstring, step 3).

    ``h_a_m``, ``h_b_m``: antenna heights above ground of the two ends; ``drone_h_m``: the (lower)
    drone end's height for links with a drone end (NaN otherwise); ``blocker_m``: NLOSv blocker top
    above ground (NaN otherwise). Every array (P,). ``overrides``: link type -> name of a model of
    :data:`cosim.comm.models.LINK_MODELS` used for every pair of that type instead of the default.
    """
    p = len(types)
    pl = np.zeros(p)
    sigma = np.zeros(p)
    dcorr = np.zeros(p)
    model = [""] * p
    los = state == LOS
    nlos = state == NLOS
    h_bs, h_ut = np.maximum(h_a_m, h_b_m), np.minimum(h_a_m, h_b_m)
    blk_mean, blk_std = ch.nlosv_blockage_db(d3d_m, h_a_m, h_b_m, np.nan_to_num(blocker_m, nan=-np.inf))
    blk_mean = np.where(state == NLOSV, blk_mean, 0.0)
    blk_std = np.where(state == NLOSV, blk_std, 0.0)
    types_a = np.array(types)
    h = np.maximum(np.where(np.isfinite(drone_h_m), drone_h_m, 100.0), 1.0)  # only aerial rows are kept
    geometry = PairGeometry(d3d_m, d2d_m, h_bs, h_ut, h, fc_ghz, ag_model)

    def put(mask: np.ndarray, name: str) -> None:
        if not mask.any():
            return
        m = LINK_MODELS.get(name)(geometry)
        idx = np.nonzero(mask)[0]
        pl[idx] = np.where(nlos[idx], np.asarray(m.nlos_db)[idx], np.asarray(m.los_db)[idx] + blk_mean[idx])
        s = np.where(nlos[idx], np.asarray(m.sigma_nlos_db)[idx] if np.ndim(m.sigma_nlos_db) else m.sigma_nlos_db,
                     np.asarray(m.sigma_los_db)[idx] if np.ndim(m.sigma_los_db) else m.sigma_los_db)
        sigma[idx] = np.hypot(s, blk_std[idx])
        dcorr[idx] = np.where(los[idx], m.decorrelation_m[0], m.decorrelation_m[1])
        for i in idx:
            model[i] = name

    drone = np.isin(types_a, ("vehicle-drone", "rsu-drone", "drone-drone"))
    aerial = drone & (drone_h_m > ch.AV_MIN_HEIGHT_M[ag_model])
    groups = [
        (types_a == "vehicle-vehicle", f"tr37885_{setting}"),
        (np.isin(types_a, ("vehicle-rsu", "rsu-rsu")) | (drone & ~aerial), "tr38901_umi_sc"),
        (aerial & (types_a != "drone-drone"), f"tr36777_{ag_model}"),
        (aerial & (types_a == "drone-drone"), "free_space"),
    ]
    for link, name in (overrides or {}).items():
        chosen = types_a == link
        groups = [(mask & ~chosen, n) for mask, n in groups] + [(chosen, name)]
    for mask, name in groups:
        put(mask, name)
    return PairChannel(pl, sigma, dcorr, tuple(model))


def check_link_models(overrides: Mapping[str, str]) -> None:
    """``comm.link_models`` names known link types and registered models (else an InputError naming them)."""
    for link, name in overrides.items():
        if link not in LINK_TYPES:
            raise InputError(f"comm.link_models: unknown link type {link!r}; known: {', '.join(LINK_TYPES)}")
        LINK_MODELS.get(name)


def compute_links(snapshot: WorldSnapshot, scene: LinkScene, spec: Any, map_kind: str, tick_ns: int,
                  fading: FadingState | None, rng: np.random.Generator) -> tuple[LinkSet, FadingState]:
    """Every ordered link of ``snapshot``'s agents (see the module docstring).

    ``spec`` is a :class:`cosim.scenario.model.CommSpec`; ``map_kind`` the world's kind (the
    setting when ``spec.environment`` is auto); ``fading`` the state returned for the previous tick
    (None at the first); ``rng`` draws exactly one standard normal per unordered pair, in pair order.
    """
    agents = snapshot.agents
    ids = tuple(a.agent_id for a in agents)
    n = len(agents)
    pairs = list(combinations(range(n), 2))
    ia = np.array([i for i, _ in pairs], np.int64)
    ib = np.array([j for _, j in pairs], np.int64)
    ant = antenna_positions(agents, spec)
    a_m, b_m = ant[ia], ant[ib]
    d3d = np.linalg.norm(b_m - a_m, axis=1)
    d2d = np.linalg.norm((b_m - a_m)[:, :2], axis=1)
    own = np.array([a.track_id if a.track_id is not None else -1 for a in agents], np.int64)
    state, blocker_z = line_of_sight(scene, a_m, b_m, own[ia], own[ib], snapshot.actors)

    ground = scene.ground_z_m
    kinds = [a.kind for a in agents]
    type_of = {(a, b): link_type(a, b) for a in set(kinds) for b in set(kinds)}
    types = [type_of[kinds[i], kinds[j]] for i, j in pairs]
    h_all = ant[:, 2] - ground
    h_a, h_b = h_all[ia], h_all[ib]
    is_drone = np.array([k == "drone" for k in kinds], bool)
    drone_h = np.where(is_drone[ia] & is_drone[ib], np.minimum(h_a, h_b),
                       np.where(is_drone[ia], h_a, np.where(is_drone[ib], h_b, np.nan)))
    setting = setting_of(spec, map_kind)
    ag_model = air_ground_model_of(spec, setting)
    chan = pair_channels(types, state, d3d, d2d, h_a, h_b, drone_h, blocker_z - ground, setting, ag_model,
                         spec.carrier_ghz, getattr(spec, "link_models", None))

    innovation = rng.standard_normal(len(pairs))
    if fading is not None and fading.agent_ids == ids:
        moved = np.linalg.norm(ant - fading.antennas_m, axis=1)
        rho = np.exp(-(moved[ia] + moved[ib]) / chan.decorrelation_m)
        z = rho * fading.z + np.sqrt(1.0 - rho**2) * innovation
    else:
        z = innovation
    sf = chan.sigma_db * z if spec.shadow_fading else np.zeros(len(pairs))

    bandwidth_hz = spec.bandwidth_mhz * 1e6
    noise = phy.noise_dbm(bandwidth_hz, spec.noise_figure_db)
    rx = phy.rx_power_dbm(spec.tx_power_dbm, 2.0 * spec.antenna_gain_dbi, chan.path_loss_db, sf)
    snr = rx - noise
    per = phy.per(snr, spec.mcs, spec.shannon_efficiency, spec.per_waterfall_db)
    mcs_rate = phy.mcs_rate_bps(spec.mcs, bandwidth_hz, spec.overhead_share)
    delay = phy.delay_ms(spec.message_bytes, mcs_rate, spec.processing_delay_ms, spec.access_delay_ms)
    delivery = np.where(delay * 1e6 <= tick_ns, 1.0 - per, 0.0)

    # both directions of every pair, ordered by (tx, rx) in agent order
    order = sorted([(i, j, k) for k, (i, j) in enumerate(pairs)] + [(j, i, k) for k, (i, j) in enumerate(pairs)])
    tx = tuple(ids[i] for i, _, _ in order)
    rx_ids = tuple(ids[j] for _, j, _ in order)
    k = np.array([k for _, _, k in order], np.int64)
    links = LinkSet(
        tick=snapshot.tick,
        t_ns=snapshot.t_ns,
        tx=tx,
        rx=rx_ids,
        link_type=tuple(types[i] for i in k),
        los=tuple(LOS_STATES[s] for s in state[k]),
        model=tuple(chan.model[i] for i in k),
        distance_m=d3d[k],
        path_loss_db=chan.path_loss_db[k],
        shadow_fading_db=sf[k],
        rx_power_dbm=rx[k],
        snr_db=snr[k],
        per=per[k],
        rate_bps=mcs_rate * (1.0 - per[k]),
        capacity_bps=phy.capacity_bps(snr[k], bandwidth_hz, spec.shannon_efficiency),
        delay_ms=np.full(len(k), delay),
        delivery=delivery[k],
    )
    return links, FadingState(ids, z, ant)


class LinkModel:
    """:func:`compute_links` tick after tick for one episode (carries the fading state).

    The generator of tick ``k`` is ``default_rng([seed, k, COMM_STREAM])``: the draws of one tick do
    not depend on how many ticks came before or on any other random stream.
    """

    def __init__(self, spec: Any, scene: LinkScene, map_kind: str, seed: int, tick_ns: int):
        check_link_models(getattr(spec, "link_models", {}))
        self.spec = spec
        self.scene = scene
        self.map_kind = map_kind
        self.seed = seed
        self.tick_ns = tick_ns
        self._fading: FadingState | None = None

    def step(self, snapshot: WorldSnapshot) -> LinkSet:
        rng = np.random.default_rng([self.seed, snapshot.tick, COMM_STREAM])
        links, self._fading = compute_links(snapshot, self.scene, self.spec, self.map_kind, self.tick_ns,
                                            self._fading, rng)
        return links

    def message(self, snapshot: WorldSnapshot) -> tuple[str, tuple[str, dict[str, Any], dict[str, Any]]]:
        """The tick's ``/comm/links`` (topic, (schema name, JSON schema, payload)) for the episode writer."""
        s = self.spec
        payload = links_payload(self.step(snapshot), s.mcs, s.message_bytes, s.bandwidth_mhz * 1e6)
        return TOPIC, (SCHEMA_NAME, LINK_ARRAY_SCHEMA, payload)


__all__ = ["COMM_STREAM", "LINK_TYPES", "FadingState", "LinkModel", "compute_links", "link_type"]
