"""Colour filter array (CFA) geometry: which colour each photosite of a Bayer sensor sees (docs/COLOUR.md).

A Bayer pattern is named by the colours of its top-left 2 x 2 block read row by row (`rggb`: red at (0, 0),
green at (0, 1) and (1, 0), blue at (1, 1)). Channels are numbered R = 0, G = 1, B = 2 everywhere in nrhdr;
colour images are planar float32 (3, H, W). A monochrome sensor has the CFA `none`.
"""
from __future__ import annotations

import numpy as np

NONE = "none"
PATTERNS = ("rggb", "bggr", "grbg", "gbrg")     # the four Bayer phases (GStreamer video/x-bayer formats)
CFAS = (NONE,) + PATTERNS
R, G, B = 0, 1, 2
CHANNEL_NAMES = ("R", "G", "B")
_INDEX = {"r": R, "g": G, "b": B}
# ND layouts over a Bayer CFA (mask.cfa_mask, docs/SIMULATOR.md): independent of it, balanced per 2 x 2
# sub-lattice, or the regular Assorted-Pixels block checkerboard; `mask.nd_layout_of` names a mask without ND
# pixels NO_ND
ND_LAYOUTS = ("independent", "balanced", "regular")
DEFAULT_ND_LAYOUT = "balanced"
NO_ND = "none"


def check(cfa, what: str = "cfa") -> str:
    """`cfa` as a CFA name (lower case); ValueError naming `what` when it is none of CFAS."""
    name = cfa.lower() if isinstance(cfa, str) else cfa
    if name not in CFAS:
        raise ValueError(f"{what}: must be one of {', '.join(CFAS)}, got {cfa!r}")
    return name


def is_colour(cfa) -> bool:
    """True for a Bayer CFA, False for `none` (monochrome) or None."""
    return cfa is not None and check(cfa) != NONE


def block(cfa: str) -> np.ndarray:
    """The 2 x 2 channel indices (uint8) of a Bayer pattern's top-left block."""
    name = check(cfa)
    if name == NONE:
        raise ValueError("cfa: 'none' (monochrome) has no colour block")
    return np.array([[_INDEX[name[0]], _INDEX[name[1]]], [_INDEX[name[2]], _INDEX[name[3]]]], np.uint8)


def channel_index(cfa: str, height: int, width: int) -> np.ndarray:
    """uint8 (height, width): the channel (R = 0, G = 1, B = 2) each photosite sees."""
    b = block(cfa)
    out = np.empty((height, width), np.uint8)
    for dy in range(2):
        for dx in range(2):
            out[dy::2, dx::2] = b[dy, dx]
    return out


def channel_masks(cfa: str, height: int, width: int) -> np.ndarray:
    """bool (3, height, width): photosites of R, G and B."""
    idx = channel_index(cfa, height, width)
    return np.stack([idx == c for c in range(3)])


def mosaic(rgb: np.ndarray, cfa: str) -> np.ndarray:
    """The CFA image of a planar (3, H, W) or interleaved (H, W, 3) colour image: each photosite keeps its
    own channel (float32 (H, W))."""
    a = np.asarray(rgb)
    if a.ndim != 3 or 3 not in (a.shape[0], a.shape[2]):
        raise ValueError(f"mosaic: need a (3, H, W) or (H, W, 3) image, got shape {a.shape}")
    planar = a if a.shape[0] == 3 else np.moveaxis(a, 2, 0)
    idx = channel_index(cfa, planar.shape[1], planar.shape[2])
    return np.take_along_axis(planar, idx[None].astype(np.intp), axis=0)[0].astype(np.float32)
