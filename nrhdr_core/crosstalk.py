"""Crosstalk (paper section 3): sensor model and correction. (Interface stub; the full model, LUT and
neighbour-kernel correction land with the crosstalk issue.)"""
from __future__ import annotations

import numpy as np

MODES = ("lut", "kernel", "off")


def correct(values: np.ndarray, state: np.ndarray, profile, mode: str = "lut"):
    """Correct attenuated pixels in place (paper 3.2). Without a calibration in the profile, or with
    mode 'off', frames pass through unchanged. Returns (values, state)."""
    if mode not in MODES:
        raise ValueError(f"crosstalk mode must be one of {MODES}, got {mode!r}")
    if mode == "off" or profile.crosstalk is None:
        return values, state
    raise NotImplementedError("crosstalk correction with a calibration is not implemented yet")


def save_calibration(calib, path) -> dict:
    raise NotImplementedError


def load_calibration(entry: dict, base_dir, shape):
    raise NotImplementedError


def warmup() -> None:
    pass
