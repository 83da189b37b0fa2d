"""Per-frame validity, pixel selection and ND scaling (paper section 2.3, Eq. 3).

`classify(raw, profile, mode)` turns a raw frame into the HDR frame of docs/ARCHITECTURE.md: float32 linear
DN values (attenuated pixels scaled by ND, Eq. 3) and a uint8 state per pixel. Missing pixels carry the
bound their state implies: a clipped pixel's value is its lower bound, a too-dark pixel's its upper bound.

Selection modes (section 2.3, Fig. 3/4):
- ``all``: every pixel that is neither clipped nor below SNR = 0 dB is valid ("valid pixel").
- ``best``: as ``all``, but an attenuated pixel is discarded when a regular pixel among its 8 neighbours is
  valid ("best pixel only": at most half the pixels known in mid-tones).
- ``threshold``: attenuated pixels below ``l_min`` (code above black) are invalid; the paper's practical
  choice and the default.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from .profile import CameraProfile
from .sensor import zero_db_signal_dn

VALID = 0
CLIPPED = 1
DARK = 2
DISCARDED = 3
UNCALIBRATED = 4
REASON_MASK = 0x0F
RECONSTRUCTED = 0x40
ATTENUATED = 0x80

MODES = ("all", "best", "threshold")
_MODE_ID = {m: i for i, m in enumerate(MODES)}


def known_mask(state: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """True where the pixel was measured and is trusted (reason VALID). `out`: optional bool array."""
    state = np.asarray(state)
    if state.ndim != 2 or state.dtype != np.uint8:
        return np.equal(state & REASON_MASK, VALID, out=out)
    if out is None:
        out = np.empty(state.shape, np.bool_)
    _known_kernel(state, out)
    return out


def missing_mask(state: np.ndarray) -> np.ndarray:
    """True where the pixel must be reconstructed: not VALID and not yet RECONSTRUCTED."""
    return ((state & REASON_MASK) != VALID) & ((state & RECONSTRUCTED) == 0)


def bounds(values: np.ndarray, state: np.ndarray, lower: np.ndarray | None = None,
           upper: np.ndarray | None = None):
    """(lower, upper) float32 arrays, NaN where there is no bound: CLIPPED pixels are at least their
    value, DARK pixels at most their value (paper 2.3; fse-reference 'Quirks'). `lower`/`upper`:
    optional float32 arrays to fill."""
    values = np.asarray(values)
    state = np.asarray(state)
    if values.ndim != 2 or state.dtype != np.uint8 or values.shape != state.shape:
        reason = state & REASON_MASK
        lo = np.where(reason == CLIPPED, values, np.nan).astype(np.float32)
        hi = np.where(reason == DARK, values, np.nan).astype(np.float32)
        if lower is not None:
            lower[...] = lo
            lo = lower
        if upper is not None:
            upper[...] = hi
            hi = upper
        return lo, hi
    _, _, lower, upper = prepare(values, state, lower=lower, upper=upper)
    return lower, upper


@njit(cache=True, nogil=True, parallel=True)
def _known_kernel(state, known):
    h, w = state.shape
    for y in prange(h):
        for x in range(w):
            known[y, x] = (state[y, x] & REASON_MASK) == VALID


@njit(cache=True, nogil=True, parallel=True)
def _prepare_kernel(values, state, known, lower, upper, with_bounds):
    """One pass: known mask, bounds, counts of missing (not VALID, not RECONSTRUCTED) and of
    not-VALID pixels."""
    h, w = state.shape
    nan = np.float32(np.nan)
    n_miss = 0
    n_unknown = 0
    for y in prange(h):
        cm = 0
        cu = 0
        for x in range(w):
            st = state[y, x]
            r = st & REASON_MASK
            k = r == VALID
            known[y, x] = k
            cu += 0 if k else 1
            cm += 1 if (not k and (st & RECONSTRUCTED) == 0) else 0
            if with_bounds:
                v = np.float32(values[y, x])
                lower[y, x] = v if r == CLIPPED else nan
                upper[y, x] = v if r == DARK else nan
        n_miss += cm
        n_unknown += cu
    return n_miss, n_unknown


def prepare(values: np.ndarray, state: np.ndarray, known: np.ndarray | None = None,
            lower: np.ndarray | None = None, upper: np.ndarray | None = None, with_bounds: bool = True):
    """Everything reconstruction needs from an HDR frame in one parallel pass: returns
    (n_missing, known, lower, upper) = (count of `missing_mask`, `known_mask`, `bounds`); lower/upper
    are None when `with_bounds` is False. Output arrays may be passed in (no per-frame allocation)."""
    n_miss, _, known, lower, upper = _prepare(values, state, known, lower, upper, with_bounds)
    return n_miss, known, lower, upper


def _prepare(values, state, known, lower, upper, with_bounds):
    h, w = state.shape
    if known is None:
        known = np.empty((h, w), np.bool_)
    if with_bounds:
        if lower is None:
            lower = np.empty((h, w), np.float32)
        if upper is None:
            upper = np.empty((h, w), np.float32)
        lo_a, hi_a = lower, upper
    else:
        lower = upper = None
        lo_a = hi_a = np.empty((1, 1), np.float32)
    for name, a, dt in (("known", known, np.bool_), ("lower", lo_a, np.float32), ("upper", hi_a, np.float32)):
        if a.dtype != dt or (a.shape != (h, w) and a.shape != (1, 1)):
            raise ValueError(f"{name} must be a {np.dtype(dt).name} array of shape {(h, w)}")
    n_miss, n_unknown = _prepare_kernel(values, state, known, lo_a, hi_a, bool(with_bounds))
    return int(n_miss), int(n_unknown), known, lower, upper


@njit(cache=True, nogil=True, parallel=True)
def _write_back_kernel(values, state, result, flag):
    h, w = state.shape
    n = 0
    for y in prange(h):
        c = 0
        for x in range(w):
            st = state[y, x]
            m = (st & REASON_MASK) != VALID and (st & RECONSTRUCTED) == 0
            values[y, x] = result[y, x] if m else values[y, x]
            state[y, x] = (st | flag) if m else st
            c += 1 if m else 0
        n += c
    return n


def write_back(values: np.ndarray, state: np.ndarray, result: np.ndarray) -> int:
    """Copy `result` into `values` at the missing pixels (`missing_mask`) and set their RECONSTRUCTED
    bit, in one pass (in place; `result` may be `values`). Returns the number of pixels written."""
    return int(_write_back_kernel(values, state, result, np.uint8(RECONSTRUCTED)))


@njit(cache=True, nogil=True, parallel=True)
def _classify_kernel(raw, mask, black, clip_code, nd, dark_att, dark_reg, mode, values, state):
    h, w = raw.shape
    for y in prange(h):
        for x in range(w):
            code = np.float32(raw[y, x])
            att = mask[y, x]
            s = np.float32(nd) if att else np.float32(1.0)
            sig = code - np.float32(black)
            st = np.uint8(ATTENUATED) if att else np.uint8(0)
            if raw[y, x] >= clip_code:
                values[y, x] = (np.float32(clip_code) - np.float32(black)) * s
                state[y, x] = st | np.uint8(CLIPPED)
                continue
            thr = np.float32(dark_att) if att else np.float32(dark_reg)
            if sig < thr:
                values[y, x] = thr * s
                state[y, x] = st | np.uint8(DARK)
                continue
            values[y, x] = sig * s
            reason = VALID
            if mode == 1 and att:
                # best pixel only: drop when a valid regular neighbour exists (8-neighbourhood)
                for dy in range(-1, 2):
                    yy = y + dy
                    if yy < 0 or yy >= h:
                        continue
                    for dx in range(-1, 2):
                        xx = x + dx
                        if xx < 0 or xx >= w or (dy == 0 and dx == 0) or mask[yy, xx]:
                            continue
                        c2 = raw[yy, xx]
                        if c2 < clip_code and np.float32(c2) - np.float32(black) >= np.float32(dark_reg):
                            reason = DISCARDED
            state[y, x] = st | np.uint8(reason)


def classify(raw: np.ndarray, profile: CameraProfile, mode: str = "threshold", l_min: float | None = None,
             values: np.ndarray | None = None, state: np.ndarray | None = None):
    """Classify a raw frame (uint16 (H, W)) into (values float32, state uint8), Eq. 3. Output arrays may be
    passed in (e.g. mapped GStreamer memory) and are filled in place. `l_min` overrides the profile's."""
    if mode not in _MODE_ID:
        raise ValueError(f"selection mode must be one of {MODES}, got {mode!r}")
    raw = np.asarray(raw)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise ValueError(f"raw frame must be a 2-D uint16 array, got {raw.dtype} {raw.shape}")
    if raw.shape != profile.mask.shape:
        raise ValueError(f"raw frame is {raw.shape[1]}x{raw.shape[0]} but the profile's mask is "
                         f"{profile.width}x{profile.height}")
    if values is None:
        values = np.empty(raw.shape, np.float32)
    if state is None:
        state = np.empty(raw.shape, np.uint8)
    s0 = zero_db_signal_dn(profile)
    lm = profile.l_min if l_min is None else float(l_min)
    if mode == "threshold":
        dark_att, dark_reg = lm, -np.inf
    else:
        dark_att, dark_reg = s0, s0
    _classify_kernel(raw, profile.mask, float(profile.black_level), int(profile.clip_code),
                     float(profile.nd), float(dark_att), float(dark_reg), _MODE_ID[mode], values, state)
    return values, state


def valid_ratio(state: np.ndarray) -> float:
    """Share of known pixels (paper Fig. 4 / 8b)."""
    return float(np.mean(known_mask(state)))


def warmup() -> None:
    """Compile the kernel on a tiny frame (elements call this in do_start, never at import)."""
    from .profile import make
    p = make(np.zeros((2, 2), bool))
    classify(np.zeros((2, 2), np.uint16), p)
