"""Sensor model of the non-regular ND camera (paper section 2.3, Eq. 1-7) plus read noise, quantisation
and clipping; crosstalk, PRNU and DSNU come from an optional `crosstalk.SensorModel` (paper section 3).

Scenes are given as `flux_dn`: the noise-free signal, in DN above black, that an unattenuated pixel would
record without clipping (the simulator's ground truth, same units as the HDR frames).
"""
from __future__ import annotations

import math

import numpy as np

from .profile import CameraProfile


def expected_electrons(flux_dn: np.ndarray, profile: CameraProfile) -> np.ndarray:
    """Mean photo-electrons per pixel: mu = flux/gain for regular pixels, mu/ND behind the filter (Eq. 2)."""
    e = np.asarray(flux_dn, dtype=np.float64) / profile.gain
    return np.where(profile.mask, e / profile.nd, e)


def capture(flux_dn: np.ndarray, profile: CameraProfile, rng: np.random.Generator,
            sensor_model=None, shot_noise: bool = True) -> np.ndarray:
    """One raw frame (uint16 codes): ND attenuation (Eq. 2), optional crosstalk/PRNU/DSNU
    (`sensor_model.apply(electrons, profile, rng)`), Poisson shot noise (variance = mean, section 2.3),
    full-well clipping, Gaussian read noise, gain, black level, rounding and ADC clipping."""
    flux = np.asarray(flux_dn)
    if flux.shape != profile.mask.shape:
        raise ValueError(f"scene is {flux.shape[1]}x{flux.shape[0]} but the profile's mask is "
                         f"{profile.width}x{profile.height}")
    if not np.isfinite(flux).all() or (flux < 0).any():
        raise ValueError("scene flux must be finite and >= 0")
    e = expected_electrons(flux, profile)
    if sensor_model is not None:
        e = sensor_model.apply(e, profile, rng)
    if shot_noise:
        # Poisson for the bulk; the normal approximation for enormous means keeps int64 safe.
        big = e > 1e7
        n = rng.poisson(np.where(big, 0.0, e)).astype(np.float64)
        if big.any():
            n[big] = e[big] + np.sqrt(e[big]) * rng.standard_normal(int(big.sum()))
    else:
        n = e
    n = np.minimum(n, profile.full_well)
    if profile.read_noise > 0:
        n = n + profile.read_noise * rng.standard_normal(n.shape)
    code = np.rint(n * profile.gain + profile.black_level)
    return np.clip(code, 0, profile.max_code).astype(np.uint16)


# ---- the ideal model's SNR (shot noise only), Eq. 4-7 ----------------------------------------------

def snr_regular_db(mu_electrons):
    """Eq. 4 with sigma^2 = mu (shot noise): SNR_d0 = 20 log10(mu / sqrt(mu))."""
    mu = np.asarray(mu_electrons, dtype=np.float64)
    return 20.0 * np.log10(mu / np.sqrt(mu))


def snr_attenuated_db(mu_electrons, nd: float):
    """Eq. 5: SNR_d1 = 20 log10(mu_d0 / (sqrt(ND) sigma_d0)), mu_d0 the unattenuated pixel's electrons."""
    mu = np.asarray(mu_electrons, dtype=np.float64)
    return 20.0 * np.log10(mu / (math.sqrt(nd) * np.sqrt(mu)))


def snr_global_db(mu_electrons, nd: float):
    """Eq. 7: SNR_global = 20 log10(sqrt(2 / (1 + ND)) mu_d0 / sigma_d0), all pixels valid and scaled."""
    mu = np.asarray(mu_electrons, dtype=np.float64)
    return 20.0 * np.log10(math.sqrt(2.0 / (1.0 + nd)) * mu / np.sqrt(mu))


def zero_db_signal_dn(profile: CameraProfile) -> float:
    """Signal s (DN above black) where SNR = 0 dB for this sensor: s^2 = g s + (g sigma_r)^2 + 1/12,
    with shot, read and quantisation noise (the 'SNR < 0 dB' lower limit of paper Fig. 3/4)."""
    g = profile.gain
    c = (g * profile.read_noise) ** 2 + 1.0 / 12.0
    return 0.5 * (g + math.sqrt(g * g + 4.0 * c))
