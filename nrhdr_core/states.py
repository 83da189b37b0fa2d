"""Pixel states of the HDR frame: the one definition (paper 2.3, Eq. 3; docs/ARCHITECTURE.md "State byte").

The state byte of a pixel is ``reason | flags``: the low four bits (``REASON_MASK``) say why the value is
what it is, the high bits are flags. A pixel is *known* when its reason is ``VALID``; every other reason
makes it *missing* until the reconstruction fills it and sets ``RECONSTRUCTED``.
"""
from __future__ import annotations

# reasons (state & REASON_MASK)
VALID = 0          # measured linear DN
CLIPPED = 1        # code >= clip code: the value is a lower bound
DARK = 2           # attenuated pixel below l_min: the value is an upper bound
DISCARDED = 3      # dropped: by the "best pixel only" selection, or a defect pixel of the profile (hot,
                   # dead, stuck); the value is the measurement
UNCALIBRATED = 4   # outside the crosstalk calibration (or more spill than signal): the value is an estimate
NOISY = 5          # attenuated pixel below l_min kept as a noisy measurement (dark_policy="weighted")

# masks and flags
REASON_MASK = 0x0F
FLAG_MASK = 0xF0
RECONSTRUCTED = 0x40   # filled by the reconstruction (the reason is kept)
ATTENUATED = 0x80      # the pixel sits behind an ND filter

REASON_NAMES = {VALID: "valid", CLIPPED: "clipped", DARK: "dark", DISCARDED: "discarded",
                UNCALIBRATED: "uncalibrated", NOISY: "noisy"}
