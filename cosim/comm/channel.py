"""Path loss and shadow fading of the 3GPP channel models, one function per model and state.

Every function takes numpy arrays (or floats) and returns the same shape. Distances are 3D (``d3d_m``)
or horizontal (``d2d_m``) in metres, heights above ground in metres, the carrier ``fc_ghz`` in GHz;
losses and standard deviations in dB. Distances below 1 m are taken as 1 m (every formula has a
log10 of the distance; the tables start far above that).

Sources (the formula text is quoted in each docstring):

- 3GPP TR 37.885 V15.3.0, *Study on evaluation methodology of new V2X use cases for LTE and NR*:
  Table 6.2.1-1 (V2V path loss and shadow fading), section 6.2.1 (additional vehicle blockage loss
  for NLOSv), Table 6.2.3-1 (shadow fading decorrelation distance).
- 3GPP TR 38.901 V17.0.0, *Study on channel model for frequencies from 0.5 to 100 GHz*: Table 7.4.1-1
  (UMi-Street Canyon path loss), Table 7.5-6 part 1 (shadow fading correlation distances).
- 3GPP TR 36.777 V15.0.0, *Enhanced LTE support for aerial vehicles*: Annex B, Table B-2 (path loss
  and shadow fading of aerial UEs in RMa-AV, UMa-AV and UMi-AV, by the aerial UE's height).
"""

from __future__ import annotations

import math

import numpy as np

C_MPS = 299_792_458.0  # [m/s] speed of light
#: Heights above which TR 36.777 Table B-2 gives the aerial (AV) formulas; below, the terrestrial
#: TR 38.901 model applies ("for h_UT <= 22.5 m the corresponding terrestrial model is used").
AV_MIN_HEIGHT_M = {"umi_av": 22.5, "uma_av": 22.5, "rma_av": 10.0}


def _d(d_m):
    return np.maximum(np.asarray(d_m, dtype=np.float64), 1.0)


def _log(x):
    return np.log10(np.asarray(x, dtype=np.float64))


# ------------------------------------------------------------------------------- free space


def free_space_db(d3d_m, fc_ghz: float):
    """Free-space path loss, as TR 36.777 Table B-2 (UMi-AV) writes it:
    ``PL_FS = 20 log10(d3D) + 20 log10(fc) + 32.44`` (fc in GHz)."""
    return 20.0 * _log(_d(d3d_m)) + 20.0 * math.log10(fc_ghz) + 32.44


# ------------------------------------------------------------------ TR 37.885 (V2V sidelink)


def v2v_highway_los_db(d3d_m, fc_ghz: float):
    """TR 37.885 Table 6.2.1-1, highway LOS: ``PL = 32.4 + 20 log10(d) + 20 log10(fc)``; SF std 3 dB."""
    return 32.4 + 20.0 * _log(_d(d3d_m)) + 20.0 * math.log10(fc_ghz)


def v2v_urban_los_db(d3d_m, fc_ghz: float):
    """TR 37.885 Table 6.2.1-1, urban LOS: ``PL = 38.77 + 16.7 log10(d) + 18.2 log10(fc)``; SF std 3 dB."""
    return 38.77 + 16.7 * _log(_d(d3d_m)) + 18.2 * math.log10(fc_ghz)


def v2v_urban_nlos_db(d3d_m, fc_ghz: float):
    """TR 37.885 Table 6.2.1-1, urban NLOS (building): ``PL = 36.85 + 30 log10(d) + 18.9 log10(fc)``;
    SF std 4 dB. The highway setting has no NLOS row; cosim uses this one there too."""
    return 36.85 + 30.0 * _log(_d(d3d_m)) + 18.9 * math.log10(fc_ghz)


def nlosv_blockage_db(d3d_m, h_a_m, h_b_m, h_blocker_m):
    """TR 37.885 section 6.2.1, additional vehicle blockage loss of an NLOSv link: mean and std [dB].

    - ``min(h_a, h_b) > h_blocker``: 0 dB (both antennas above the blocker);
    - ``max(h_a, h_b) < h_blocker``: mean ``9 + max(0, 15 log10(d) - 41)``, std 4.5 dB;
    - otherwise: mean ``5 + max(0, 15 log10(d) - 41)``, std 4 dB.

    The TR draws the loss from a log-normal of that mean and std; cosim adds the mean to the path
    loss and the std (in quadrature) to the link's shadow fading, so the loss stays correlated in
    time like the rest of the fading. Heights may be absolute z [m] of the same datum.
    """
    d = _d(d3d_m)
    lo = np.minimum(h_a_m, h_b_m)
    hi = np.maximum(h_a_m, h_b_m)
    extra = np.maximum(0.0, 15.0 * _log(d) - 41.0)
    above = lo > h_blocker_m
    below = hi < h_blocker_m
    mean = np.where(above, 0.0, np.where(below, 9.0 + extra, 5.0 + extra))
    std = np.where(above, 0.0, np.where(below, 4.5, 4.0))
    return mean, std


# ---------------------------------------------------------- TR 38.901 UMi-Street Canyon


def _umi_sc_breakpoint_m(h_bs_m, h_ut_m, fc_ghz: float):
    """``d'_BP = 4 h'_BS h'_UT fc / c`` with ``h' = h - 1 m`` (TR 38.901 Table 7.4.1-1 note 1; UMi's
    effective environment height is 1 m). Heights below 1.1 m are taken as 1.1 m."""
    hb = np.maximum(np.asarray(h_bs_m, np.float64), 1.1) - 1.0
    hu = np.maximum(np.asarray(h_ut_m, np.float64), 1.1) - 1.0
    return 4.0 * hb * hu * fc_ghz * 1e9 / C_MPS


def umi_sc_los_db(d3d_m, d2d_m, h_bs_m, h_ut_m, fc_ghz: float):
    """TR 38.901 Table 7.4.1-1, UMi-Street Canyon LOS (SF std 4 dB)::

        PL1 = 32.4 + 21 log10(d3D) + 20 log10(fc)                                  10 m <= d2D <= d'BP
        PL2 = 32.4 + 40 log10(d3D) + 20 log10(fc) - 9.5 log10(d'BP^2 + (hBS - hUT)^2)  d'BP <= d2D <= 5 km

    The higher end of the link is the "BS", the lower the "UT".
    """
    d3 = _d(d3d_m)
    bp = _umi_sc_breakpoint_m(h_bs_m, h_ut_m, fc_ghz)
    pl1 = 32.4 + 21.0 * _log(d3) + 20.0 * math.log10(fc_ghz)
    dh = np.asarray(h_bs_m, np.float64) - np.asarray(h_ut_m, np.float64)
    pl2 = 32.4 + 40.0 * _log(d3) + 20.0 * math.log10(fc_ghz) - 9.5 * _log(bp**2 + dh**2)
    return np.where(np.asarray(d2d_m) <= bp, pl1, pl2)


def umi_sc_nlos_db(d3d_m, d2d_m, h_bs_m, h_ut_m, fc_ghz: float):
    """TR 38.901 Table 7.4.1-1, UMi-Street Canyon NLOS (SF std 7.82 dB)::

        PL'_NLOS = 35.3 log10(d3D) + 22.4 + 21.3 log10(fc) - 0.3 (hUT - 1.5)
        PL_NLOS  = max(PL_LOS, PL'_NLOS)
    """
    los = umi_sc_los_db(d3d_m, d2d_m, h_bs_m, h_ut_m, fc_ghz)
    nlos = 35.3 * _log(_d(d3d_m)) + 22.4 + 21.3 * math.log10(fc_ghz) - 0.3 * (np.asarray(h_ut_m, np.float64) - 1.5)
    return np.maximum(los, nlos)


# ---------------------------------------------------------------- TR 36.777 aerial vehicles


def umi_av_los_db(d3d_m, h_ut_m, fc_ghz: float):
    """TR 36.777 Table B-2, UMi-AV LOS, 22.5 m < hUT <= 300 m::

        PL = max(PL_FS, 30.9 + (22.25 - 0.5 log10(hUT)) log10(d3D) + 20 log10(fc))
        SF std = max(5 exp(-0.01 hUT), 2)
    """
    d = _d(d3d_m)
    pl = 30.9 + (22.25 - 0.5 * _log(h_ut_m)) * _log(d) + 20.0 * math.log10(fc_ghz)
    return np.maximum(free_space_db(d, fc_ghz), pl)


def umi_av_nlos_db(d3d_m, h_ut_m, fc_ghz: float):
    """TR 36.777 Table B-2, UMi-AV NLOS, 22.5 m < hUT <= 300 m::

        PL = max(PL_LOS, 32.4 + (43.2 - 7.6 log10(hUT)) log10(d3D) + 20 log10(fc)),  SF std 8 dB
    """
    d = _d(d3d_m)
    pl = 32.4 + (43.2 - 7.6 * _log(h_ut_m)) * _log(d) + 20.0 * math.log10(fc_ghz)
    return np.maximum(umi_av_los_db(d, h_ut_m, fc_ghz), pl)


def uma_av_los_db(d3d_m, h_ut_m, fc_ghz: float):
    """TR 36.777 Table B-2, UMa-AV LOS, 22.5 m < hUT <= 300 m::

        PL = 28.0 + 22 log10(d3D) + 20 log10(fc),  SF std = 4.64 exp(-0.0066 hUT)

    (``h_ut_m`` is unused by the mean; it is taken for a uniform signature.)
    """
    del h_ut_m
    return 28.0 + 22.0 * _log(_d(d3d_m)) + 20.0 * math.log10(fc_ghz)


def uma_av_nlos_db(d3d_m, h_ut_m, fc_ghz: float):
    """TR 36.777 Table B-2, UMa-AV NLOS, 10 m < hUT <= 100 m (cosim also uses it above 100 m)::

        PL = -17.5 + (46 - 7 log10(hUT)) log10(d3D) + 20 log10(40 pi fc / 3),  SF std 6 dB
    """
    return -17.5 + (46.0 - 7.0 * _log(h_ut_m)) * _log(_d(d3d_m)) + 20.0 * math.log10(40.0 * math.pi * fc_ghz / 3.0)


def rma_av_los_db(d3d_m, h_ut_m, fc_ghz: float):
    """TR 36.777 Table B-2, RMa-AV LOS, 10 m < hUT <= 300 m::

        PL = max(23.9 - 1.8 log10(hUT), 20) log10(d3D) + 20 log10(40 pi fc / 3),  SF std 4.2 exp(-0.0046 hUT)
    """
    slope = np.maximum(23.9 - 1.8 * _log(h_ut_m), 20.0)
    return slope * _log(_d(d3d_m)) + 20.0 * math.log10(40.0 * math.pi * fc_ghz / 3.0)


def rma_av_nlos_db(d3d_m, h_ut_m, fc_ghz: float):
    """TR 36.777 Table B-2, RMa-AV NLOS, 10 m < hUT <= 300 m::

        PL = max(PL_LOS, -12 + (35 - 5.3 log10(hUT)) log10(d3D) + 20 log10(40 pi fc / 3)),  SF std 6 dB
    """
    d = _d(d3d_m)
    pl = -12.0 + (35.0 - 5.3 * _log(h_ut_m)) * _log(d) + 20.0 * math.log10(40.0 * math.pi * fc_ghz / 3.0)
    return np.maximum(rma_av_los_db(d, h_ut_m, fc_ghz), pl)


# ------------------------------------------------------------------------- shadow fading


def av_shadow_std_db(model: str, los: bool, h_ut_m):
    """Shadow fading std [dB] of TR 36.777 Table B-2 for ``model`` in umi_av, uma_av, rma_av."""
    h = np.asarray(h_ut_m, np.float64)
    if model == "umi_av":
        return np.maximum(5.0 * np.exp(-0.01 * h), 2.0) if los else np.full_like(h, 8.0)
    if model == "uma_av":
        return 4.64 * np.exp(-0.0066 * h) if los else np.full_like(h, 6.0)
    if model == "rma_av":
        return 4.2 * np.exp(-0.0046 * h) if los else np.full_like(h, 6.0)
    raise ValueError(f"unknown air-to-ground model {model!r}; known: umi_av, uma_av, rma_av")


#: Shadow fading decorrelation distance [m] (LOS, NLOS). V2V: TR 37.885 Table 6.2.3-1 (urban 10 / 13,
#: highway 25 / 25; NLOSv as NLOS). Terrestrial and aerial: TR 38.901 Table 7.5-6 part 1 (UMi 10 / 13,
#: UMa 37 / 50, RMa 37 / 120); the aerial models take the correlation of their terrestrial scenario.
DECORRELATION_M: dict[str, tuple[float, float]] = {
    "v2v_urban": (10.0, 13.0),
    "v2v_highway": (25.0, 25.0),
    "umi_sc": (10.0, 13.0),
    "umi_av": (10.0, 13.0),
    "uma_av": (37.0, 50.0),
    "rma_av": (37.0, 120.0),
    "free_space": (10.0, 13.0),
}
