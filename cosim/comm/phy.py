"""Link budget, packet error rate, rate and delay: from path loss to what a message experiences.

All functions are vectorised over numpy arrays. Powers in dBm, gains and losses in dB, SNR in dB,
rates in bit/s, delays in ms.
"""

from __future__ import annotations

import math

import numpy as np

THERMAL_NOISE_DBM_PER_HZ = -174.0  # [dBm/Hz] kT at 290 K

#: Modulation and coding schemes: name -> (bits per modulation symbol Qm, code rate R).
MCS_TABLE: dict[str, tuple[int, float]] = {
    "qpsk_1_3": (2, 1 / 3),
    "qpsk_1_2": (2, 1 / 2),
    "qpsk_3_4": (2, 3 / 4),
    "16qam_1_2": (4, 1 / 2),
    "16qam_3_4": (4, 3 / 4),
    "64qam_2_3": (6, 2 / 3),
    "64qam_3_4": (6, 3 / 4),
}


def mcs(name: str) -> tuple[int, float]:
    """(Qm, R) of a scheme; ``KeyError`` naming the known ones."""
    try:
        return MCS_TABLE[name]
    except KeyError:
        raise KeyError(f"unknown MCS {name!r}; known: {', '.join(MCS_TABLE)}") from None


def noise_dbm(bandwidth_hz: float, noise_figure_db: float) -> float:
    """Receiver noise power: ``-174 dBm/Hz + 10 log10(B) + NF``."""
    return THERMAL_NOISE_DBM_PER_HZ + 10.0 * math.log10(bandwidth_hz) + noise_figure_db


def rx_power_dbm(tx_power_dbm: float, gains_db: float, path_loss_db, shadow_fading_db):
    """``P_rx = P_tx + G_tx + G_rx - PL - SF`` (``gains_db`` = G_tx + G_rx; SF > 0 is extra loss)."""
    return tx_power_dbm + gains_db - np.asarray(path_loss_db) - np.asarray(shadow_fading_db)


def mcs_rate_bps(name: str, bandwidth_hz: float, overhead_share: float) -> float:
    """Data rate of a scheme over the whole channel: ``B (1 - overhead) Qm R`` [bit/s].

    One modulation symbol per Hz and second (OFDM); ``overhead_share`` is the part of the resource
    grid carrying no data. The default 0.42 is LTE-V2X sidelink's: 100 resource blocks of 180 kHz
    in 20 MHz (90 %), 9 of a subframe's 14 symbols carry PSSCH data (4 DMRS, 1 guard; 3GPP TS 36.211
    section 9.8), 0.9 x 9 / 14 = 0.58.
    """
    qm, r = mcs(name)
    return bandwidth_hz * (1.0 - overhead_share) * qm * r


def snr50_db(name: str, shannon_efficiency: float) -> float:
    """SNR [dB] at which the scheme's PER is 50 %: where the attenuated Shannon bound of 3GPP
    TR 36.942 Annex A.2 (``alpha log2(1 + SNR)``) reaches the scheme's ``Qm R`` bit per symbol:
    ``SNR50 = 10 log10(2^(Qm R / alpha) - 1)``. With alpha = 0.6 (the Annex's value) QPSK 1/2 needs
    3.4 dB, 16QAM 1/2 9.6 dB, 64QAM 3/4 22.6 dB (pessimistic at high rates, as the
    bound is)."""
    qm, r = mcs(name)
    return 10.0 * math.log10(2.0 ** (qm * r / shannon_efficiency) - 1.0)


def per(snr_db, name: str, shannon_efficiency: float, waterfall_db: float):
    """Packet error rate of one message: a logistic curve in SNR [dB], an approximation.

    ``PER = 1 / (1 + exp(k (SNR - SNR50)))`` with ``SNR50`` from :func:`snr50_db` and the slope
    ``k = 2 ln 9 / waterfall_db``, so that PER falls from 90 % to 10 % within ``waterfall_db``
    (about 2 dB for turbo and LDPC codes on long blocks in AWGN). This is the usual logistic fit of
    BLER curves, with its two parameters derived from the attenuated Shannon bound and the
    waterfall width rather than fitted to a link-level simulation: a stand-in, not a
    link-level model.
    """
    k = 2.0 * math.log(9.0) / waterfall_db
    x = np.clip(k * (np.asarray(snr_db, np.float64) - snr50_db(name, shannon_efficiency)), -700.0, 700.0)
    return 1.0 / (1.0 + np.exp(x))


def capacity_bps(snr_db, bandwidth_hz: float, shannon_efficiency: float):
    """Attenuated Shannon bound (TR 36.942 Annex A.2, without its truncation): ``alpha B log2(1 + SNR)``."""
    return shannon_efficiency * bandwidth_hz * np.log2(1.0 + 10.0 ** (np.asarray(snr_db, np.float64) / 10.0))


def delay_ms(message_bytes: int, rate_bps: float, processing_ms: float, access_ms: float) -> float:
    """Delay of one message: transmission (``8 bytes / rate``) + processing + channel access [ms]."""
    return 8.0 * message_bytes / rate_bps * 1e3 + processing_ms + access_ms
