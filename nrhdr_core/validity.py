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

ND scaling (Eq. 3, `scale_nd`): an attenuated pixel's signal (code - black) is multiplied by the ND factor,
so that every value is linear DN of a regular pixel; its bounds are scaled the same way.

Dark policy (threshold mode; docs/FSE.md "Noise-aware dark pixels"): ``threshold`` is the paper's;
``weighted`` keeps attenuated pixels between SNR 0 dB and ``WEIGHTED_LEVEL x l_min`` as NOISY measurements
that the reconstruction fuses by their noise (`reconstruction.fuse_noisy`).

Sensor formats (docs/PROFILE.md "Sensor data"): packed frames (Mono12Packed, Mono12p, Mono10p) are unpacked
and MSB-aligned codes shifted down to `bit_depth`-bit codes (`codes`, one numba pass, only for such profiles);
the clip code comes from the profile's white level and the black level is subtracted before scaling and in
the noise model (signal = code - black). Pixels of the profile's defect map (hot, dead, stuck) become
DISCARDED, missing pixels that the reconstruction fills (`_mark_defects`, a pass over the defect list only).

Colour sensors (profile.cfa a Bayer phase, docs/COLOUR.md "Validity and crosstalk per colour"): each
photosite is clipped, dark or noisy in its own channel (its own code against the same clip code and l_min:
both are levels of the photosite's signal, whatever its colour), and every rule that compares a pixel with
its neighbours uses same-colour neighbours only: the same-colour photosites of the 5 x 5 window (R and B:
2 apart; G: the diagonal neighbours and those 2 apart), i.e. the 3 x 3 of the colour plane (`cfa_neighbour`).

All of the classification is one numba pass (`_classify_kernel`); the pixel states are those of `states.py`.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from . import cfa as cfas
from .profile import PACKINGS, CameraProfile
from .scratch import planes
from .sensor import zero_db_signal_dn

from .states import (ATTENUATED, CLIPPED, DARK, DISCARDED, NOISY, REASON_MASK,  # noqa: F401 (re-exported)
                     RECONSTRUCTED, UNCALIBRATED, VALID)

MODES = ("all", "best", "threshold")
_NO_CHANNELS = np.zeros((1, 1), np.uint8)     # `_classify_kernel`'s channel plane of a monochrome sensor
DARK_POLICIES = ("threshold", "weighted")
# dark policy "weighted": attenuated pixels below WEIGHTED_LEVEL x l_min are fused measurements (NOISY);
# measured on the shared HDR scenes: x4 (l_min 100 -> 400) gains +1.2 dB log PSNR in mid-tones over x1
# and is the best of 1, 4, 10, 41 (docs/FSE.md "Noise-aware dark pixels")
WEIGHTED_LEVEL = 4.0


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
           upper: np.ndarray | None = None, cfa: str | None = None):
    """(lower, upper) float32 arrays, NaN where there is no bound: CLIPPED pixels are at least their
    value, DARK pixels at most their value (paper 2.3; fse-reference 'Quirks'); a clipped regular pixel
    whose attenuated neighbours are all clipped too is at least the smallest of their lower bounds
    (`_clip_lower_at`: light that saturates the ND pixels around it saturates it at least as much).
    `lower`/`upper`: optional float32 arrays to fill. `cfa`: the mosaic's Bayer phase (None / "none":
    monochrome): the neighbour rule then takes same-colour pixels only (`cfa_neighbour`). One numba pass
    (`prepare`)."""
    values = np.asarray(values)
    state = np.asarray(state)
    if values.ndim != 2 or state.dtype != np.uint8 or values.shape != state.shape:
        reason = state & REASON_MASK
        lo = np.where(reason == CLIPPED, values, np.nan).astype(np.float32)   # odd input: no neighbour rule
        hi = np.where(reason == DARK, values, np.nan).astype(np.float32)
        if lower is not None:
            lower[...] = lo
            lo = lower
        if upper is not None:
            upper[...] = hi
            hi = upper
        return lo, hi
    _, _, lower, upper = prepare(values, state, lower=lower, upper=upper, cfa=cfa)
    return lower, upper


@njit(cache=True, nogil=True, parallel=True)
def _known_kernel(state, known):
    h, w = state.shape
    for y in prange(h):
        for x in range(w):
            known[y, x] = (state[y, x] & REASON_MASK) == VALID


@njit(cache=True, nogil=True, parallel=True)
def _prepare_kernel(values, state, known, lower, upper, with_bounds, chan, coloured):
    """One pass: known mask, bounds, counts of missing (not VALID, not RECONSTRUCTED) and of
    not-VALID pixels. The clipped-neighbour bound is computed per row from column aggregates
    (`clip_lower_row`; a Bayer mosaic, `coloured` with its channel plane `chan`: from same-colour pixels,
    `clip_lower_row_cfa`), only in rows that have a clipped regular pixel."""
    h, w = state.shape
    nan = np.float32(np.nan)
    n_miss = 0
    n_unknown = 0
    for y in prange(h):
        if with_bounds and row_has_clipped_regular(state, y):
            # lower[y, x] = the rule's bound (NaN: none)
            if coloured:
                clip_lower_row_cfa(values, state, chan, y, lower[y])
            else:
                clip_lower_row(values, state, y, lower[y])
        cm = 0
        cu = 0
        for x in range(w):
            # branch-free (selects and bitwise &): the states of a random mask defeat branch prediction
            st = state[y, x]
            r = st & REASON_MASK
            k = r == VALID
            known[y, x] = k
            cu += np.int64(not k)
            cm += np.int64((not k) & ((st & RECONSTRUCTED) == 0))
            if with_bounds:
                v = np.float32(values[y, x])
                cl = r == CLIPPED
                lo = v if cl else nan
                m = lower[y, x]
                # saturated ND neighbours imply more for a clipped regular pixel
                lo = m if (cl & ((st & ATTENUATED) == 0) & (m == m) & (m > v)) else lo
                lower[y, x] = lo
                upper[y, x] = v if r == DARK else nan
        n_miss += cm
        n_unknown += cu
    return n_miss, n_unknown


@njit(cache=True, nogil=True, inline="always")
def row_has_clipped_regular(state, y):
    """True if row y has a clipped pixel without ND filter (the only pixels the neighbour rule raises)."""
    w = state.shape[1]
    for x in range(w):
        if (state[y, x] & (ATTENUATED | REASON_MASK)) == CLIPPED:
            return True
    return False


@njit(cache=True, nogil=True)
def clip_lower_row(values, state, y, mrow):
    """`_clip_lower_at` for every clipped regular pixel of row y, written into mrow[x] (other entries
    of mrow are overwritten with scratch values): the 3 x 3 test from per-column aggregates of rows
    y-1..y+1 (count of attenuated pixels, any of them not clipped, smallest clipped value), branch-free
    so it vectorises; the rare pixel without an attenuated 3 x 3 neighbour takes the 5 x 5 scan. Same
    result as `_clip_lower_at` (a minimum does not depend on the scan order)."""
    h, w = state.shape
    natt = np.zeros(w, np.int32)
    bad = np.zeros(w, np.int32)
    mn = np.full(w, np.inf, np.float32)
    n3 = np.empty(w, np.int32)
    for yy in range(max(y - 1, 0), min(y + 2, h)):
        clip_columns(values, state, yy, natt, bad, mn)
    none = _clip_combine(state, y, natt, bad, mn, n3, mrow)
    x = 0
    while none and x < w:         # no attenuated pixel in the 3 x 3 (a few per row at most): 5 x 5
        if n3[x] == 0 and (state[y, x] & (ATTENUATED | REASON_MASK)) == CLIPPED:
            mrow[x] = _clip_lower_at(values, state, y, x, h, w)
            none -= 1
        x += 1


@njit(cache=True, nogil=True)
def clip_columns(values, state, yy, natt, bad, mn):
    """Add row yy to the column aggregates of `clip_lower_row` (branch-free)."""
    w = state.shape[1]
    for x in range(w):
        s2 = state[yy, x]
        att = (s2 & ATTENUATED) != 0
        cl = (s2 & REASON_MASK) == CLIPPED
        natt[x] += np.int32(att)
        bad[x] |= np.int32(att & ~cl)
        v = np.float32(values[yy, x])
        mx = mn[x]
        mn[x] = v if (att & cl & (v < mx)) else mx


@njit(cache=True, nogil=True)
def _clip_combine(state, y, natt, bad, mn, n3, mrow):
    """3-column windows of the aggregates: mrow = their minimum when all attenuated pixels are clipped,
    else NaN; n3 = attenuated count; returns how many clipped regular pixels of row y have none."""
    w = natt.shape[0]
    nan = np.float32(np.nan)
    none = 0
    for x in range(1, w - 1):     # interior, branch-free (vectorises)
        n = natt[x - 1] + natt[x] + natt[x + 1]
        bd = bad[x - 1] | bad[x] | bad[x + 1]
        m = mn[x - 1]
        m = mn[x] if mn[x] < m else m
        m = mn[x + 1] if mn[x + 1] < m else m
        mrow[x] = nan if ((bd != 0) | (n == 0)) else m
        n3[x] = n
        none += np.int32((n == 0) & ((state[y, x] & (ATTENUATED | REASON_MASK)) == CLIPPED))
    for e in range(2 if w > 1 else 1):   # the two ends
        x = 0 if e == 0 else w - 1
        xa = x - 1 if x > 0 else x
        xb = x + 1 if x + 1 < w else x
        n = natt[x] + (natt[xa] if xa < x else 0) + (natt[xb] if xb > x else 0)
        bd = bad[xa] | bad[x] | bad[xb]
        m = mn[xa]
        m = mn[x] if mn[x] < m else m
        m = mn[xb] if mn[xb] < m else m
        mrow[x] = nan if ((bd != 0) | (n == 0)) else m
        n3[x] = n
        none += np.int32((n == 0) & ((state[y, x] & (ATTENUATED | REASON_MASK)) == CLIPPED))
    return none


def prepare(values: np.ndarray, state: np.ndarray, known: np.ndarray | None = None,
            lower: np.ndarray | None = None, upper: np.ndarray | None = None, with_bounds: bool = True,
            cfa: str | None = None):
    """Everything reconstruction needs from an HDR frame in one parallel pass: returns
    (n_missing, known, lower, upper) = (count of `missing_mask`, `known_mask`, `bounds`); lower/upper
    are None when `with_bounds` is False. Output arrays may be passed in (no per-frame allocation).
    `cfa`: the mosaic's Bayer phase for the same-colour neighbour rule (None / "none": monochrome)."""
    n_miss, _, known, lower, upper = _prepare(values, state, known, lower, upper, with_bounds, cfa)
    return n_miss, known, lower, upper


def _prepare(values, state, known, lower, upper, with_bounds, cfa=None):
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
    coloured = cfas.is_colour(cfa)
    chan = cfa_channels(cfa, h, w) if coloured else _NO_CHANNELS
    n_miss, n_unknown = _prepare_kernel(values, state, known, lo_a, hi_a, bool(with_bounds), chan, coloured)
    return int(n_miss), int(n_unknown), known, lower, upper


def cfa_channels(cfa: str, h: int, w: int) -> np.ndarray:
    """The channel plane (`cfa.channel_index`) of an (h, w) mosaic, cached per thread (one per frame size)."""
    name = cfas.check(cfa)
    return planes("validity.cfa." + name, (h, w), lambda: cfas.channel_index(name, h, w))


@njit(cache=True, nogil=True, inline="always")
def cfa_neighbour(chan, y, x, yy, xx):
    """True if (yy, xx) is a same-colour neighbour of (y, x): another photosite of the same channel in the
    5 x 5 window (R, B: 2 apart; G: diagonal or 2 apart), the 3 x 3 of the colour plane."""
    return (chan[yy, xx] == chan[y, x]) & ((yy != y) | (xx != x))


@njit(cache=True, nogil=True)
def clip_lower_row_cfa(values, state, chan, y, mrow):
    """`clip_lower_row` on a Bayer mosaic (`chan`: its channel plane): mrow[x] = `clip_lower_at_cfa` for
    every clipped regular pixel of row y (other entries of mrow are left as they are)."""
    h, w = state.shape
    for x in range(w):
        if (state[y, x] & (ATTENUATED | REASON_MASK)) == CLIPPED:
            mrow[x] = clip_lower_at_cfa(values, state, chan, y, x, h, w)


@njit(cache=True, nogil=True)
def clip_lower_at_cfa(values, state, chan, y, x, h, w):
    """`_clip_lower_at` among same-colour pixels: the smallest lower bound of the attenuated photosites of
    (y, x)'s channel in the 5 x 5 window (the colour plane's 3 x 3), else the 9 x 9 (its 5 x 5) when the
    5 x 5 has none, when all of them are clipped; NaN when some is not clipped or none is near."""
    return _clip_lower_near(values, state, chan, y, x, h, w, 2)


@njit(cache=True, nogil=True, parallel=True)
def _write_back_kernel(values, state, result, flag):
    h, w = state.shape
    n = 0
    for y in prange(h):
        c = 0
        for x in range(w):
            st = state[y, x]
            # bitwise &, not `and`: a short-circuit compiles to a branch, unpredictable on a random mask
            m = ((st & REASON_MASK) != VALID) & ((st & RECONSTRUCTED) == 0)
            values[y, x] = result[y, x] if m else values[y, x]
            state[y, x] = st | (flag * np.uint8(m))
            c += np.int64(m)
        n += c
    return n


def write_back(values: np.ndarray, state: np.ndarray, result: np.ndarray) -> int:
    """Copy `result` into `values` at the missing pixels (`missing_mask`) and set their RECONSTRUCTED
    bit, in one pass (in place; `result` may be `values`). Returns the number of pixels written."""
    return int(_write_back_kernel(values, state, result, np.uint8(RECONSTRUCTED)))


@njit(cache=True, nogil=True, inline="always")
def _clip_lower_at(values, state, y, x, h, w):
    """Smallest lower bound of the attenuated pixels around (y, x) when all of them are clipped (3 x 3,
    else 5 x 5 when the 3 x 3 has none); NaN when some is not clipped or none is near."""
    return _clip_lower_near(values, state, state, y, x, h, w, 1)


@njit(cache=True, nogil=True, inline="always")
def _clip_lower_near(values, state, chan, y, x, h, w, step):
    """The rule of `_clip_lower_at` in windows of radius `step`, then 2 `step`: step 1 every pixel,
    step 2 the same-colour pixels of a Bayer mosaic (`chan`: its channel plane; unused with step 1)."""
    for r in range(step, 3 * step, step):
        n_att = 0
        ok = True
        m = np.float32(np.inf)
        for yy in range(max(y - r, 0), min(y + r + 1, h)):
            for xx in range(max(x - r, 0), min(x + r + 1, w)):
                s2 = state[yy, xx]
                if (s2 & ATTENUATED) == 0 or (step > 1 and not cfa_neighbour(chan, y, x, yy, xx)):
                    continue
                n_att += 1
                if (s2 & REASON_MASK) != CLIPPED:
                    ok = False
                elif values[yy, xx] < m:
                    m = values[yy, xx]
        if n_att > 0:
            return m if ok else np.float32(np.nan)
    return np.float32(np.nan)


@njit(cache=True, nogil=True, inline="always")
def scale_nd(signal, attenuated, nd):
    """ND scaling (paper 2.3, Eq. 3): the signal (code - black level) of a pixel behind the ND filter times
    the filter's attenuation `nd`, a regular pixel's unchanged, so that both are linear DN of a regular
    pixel. Bounds are scaled the same way (a threshold or clip level of an attenuated pixel times `nd`)."""
    return signal * (nd if attenuated else np.float32(1.0))


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _classify_kernel(raw, mask, black, clip_code, nd, dark_att, dark_reg, weighted, best, s0, lm, values, state,
                     chan):
    """Every selection mode and dark policy of `classify` in one pass per row (paper 2.3, Eq. 3): CLIPPED at
    `clip_code` (value: the lower bound (clip - black) x s), DARK below the threshold of the pixel's kind
    (value: the threshold x s as upper bound), else VALID with its ND-scaled measurement (`scale_nd`).
    `weighted` (dark policy): DARK attenuated pixels at or above SNR 0 dB (`s0`) become NOISY with their
    measurement, those below keep l_min x ND (`lm`) as bound. `best`: a VALID attenuated pixel with a VALID
    regular pixel among its 8 neighbours (a Bayer mosaic: among its same-colour neighbours, `chan` the
    channel plane; monochrome: `chan` of shape (1, 1)) becomes DISCARDED. The per-pixel rules are written
    with arithmetic and selects, no data-dependent branches (ND and regular pixels alternate at random)."""
    h, w = raw.shape
    ndf = np.float32(nd)
    bl = np.float32(black)
    top = np.float32(clip_code) - bl
    tatt = np.float32(dark_att)
    treg = np.float32(dark_reg)
    s0f = np.float32(s0)
    lmf = np.float32(lm)
    if best and chan.shape[0] > 1:
        for y in prange(h):
            _classify_row(raw, mask, y, ndf, bl, clip_code, top, tatt, treg, weighted, s0f, lmf, values, state)
            for x in range(w):
                if state[y, x] == ATTENUATED | VALID and _valid_regular_neighbour_cfa(raw, mask, chan, y, x, bl,
                                                                                      clip_code, treg):
                    state[y, x] = ATTENUATED | DISCARDED
    elif best:
        for y in prange(h):
            _classify_row(raw, mask, y, ndf, bl, clip_code, top, tatt, treg, weighted, s0f, lmf, values, state)
            for x in range(w):
                if state[y, x] == ATTENUATED | VALID and _valid_regular_neighbour(raw, mask, y, x, bl, clip_code,
                                                                                  treg):
                    state[y, x] = ATTENUATED | DISCARDED
    else:
        for y in prange(h):
            _classify_row(raw, mask, y, ndf, bl, clip_code, top, tatt, treg, weighted, s0f, lmf, values, state)


@njit(cache=True, nogil=True, inline="always")
def _classify_row(raw, mask, y, ndf, bl, clip_code, top, tatt, treg, weighted, s0f, lmf, values, state):
    """Row y of `_classify_kernel` without the best-pixel selection."""
    for x in range(raw.shape[1]):
        r = raw[y, x]
        att = mask[y, x]
        sig = np.float32(r) - bl
        clipped = r >= clip_code
        thr = tatt if att else treg
        dark = (sig < thr) & (not clipped)
        wa = weighted & att
        noisy = dark & wa & (sig >= s0f)
        dval = scale_nd(lmf, att, ndf) if wa else scale_nd(thr, att, ndf)
        v = scale_nd(sig, att, ndf)
        v = dval if (dark & (not noisy)) else v
        v = scale_nd(top, att, ndf) if clipped else v
        values[y, x] = v
        reason = (np.uint8(CLIPPED) * np.uint8(clipped) + np.uint8(NOISY) * np.uint8(noisy)
                  + np.uint8(DARK) * np.uint8(dark & (not noisy)))
        state[y, x] = (np.uint8(ATTENUATED) * np.uint8(att)) | reason


@njit(cache=True, nogil=True, inline="always")
def _valid_regular_neighbour(raw, mask, y, x, bl, clip_code, treg):
    """True if a regular pixel among the 8 neighbours of (y, x) is valid (not clipped, signal >= treg)."""
    h, w = raw.shape
    for yy in range(max(y - 1, 0), min(y + 2, h)):
        for xx in range(max(x - 1, 0), min(x + 2, w)):
            if mask[yy, xx] or (yy == y and xx == x):
                continue
            c2 = raw[yy, xx]
            if c2 < clip_code and np.float32(c2) - bl >= treg:
                return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _valid_regular_neighbour_cfa(raw, mask, chan, y, x, bl, clip_code, treg):
    """`_valid_regular_neighbour` among the same-colour neighbours of (y, x) (`cfa_neighbour`)."""
    h, w = raw.shape
    for yy in range(max(y - 2, 0), min(y + 3, h)):
        for xx in range(max(x - 2, 0), min(x + 3, w)):
            if mask[yy, xx] or not cfa_neighbour(chan, y, x, yy, xx):
                continue
            c2 = raw[yy, xx]
            if c2 < clip_code and np.float32(c2) - bl >= treg:
                return True
    return False


class FrameError(ValueError):
    """A raw frame (or argument) classify cannot use: wrong type, shape, mode or l_min; names what is wrong."""


@njit(cache=True, nogil=True, parallel=True)
def _unpack_lsb_kernel(data, bits, out):
    """PFNC Mono10p / Mono12p: pixels as one LSB-first bit stream, lines not padded. Pixel i is bits
    i*bits .. i*bits+bits-1; for 10 and 12 bits they lie within the two bytes at (i*bits) // 8."""
    h, w = out.shape
    m = (1 << bits) - 1
    for y in prange(h):
        for x in range(w):
            off = (y * w + x) * bits
            b = off >> 3
            lo = np.uint32(data[b])
            hi = np.uint32(data[b + 1]) if b + 1 < data.shape[0] else np.uint32(0)
            out[y, x] = np.uint16(((lo | (hi << 8)) >> (off & 7)) & m)


@njit(cache=True, nogil=True, parallel=True)
def _unpack_mono12packed_kernel(data, out):
    """GigE Vision Mono12Packed: two pixels in three bytes, byte 0 = p0 bits 11..4, byte 1 = p0 bits 3..0
    (low nibble) and p1 bits 3..0 (high nibble), byte 2 = p1 bits 11..4; lines not padded."""
    h, w = out.shape
    for y in prange(h):
        for x in range(w):
            i = y * w + x
            b = (i >> 1) * 3
            mid = np.uint16(data[b + 1])
            if i & 1:
                out[y, x] = (np.uint16(data[b + 2]) << 4) | (mid >> 4)
            else:
                out[y, x] = (np.uint16(data[b]) << 4) | (mid & np.uint16(0x0F))


@njit(cache=True, nogil=True, parallel=True)
def _shift_kernel(raw, shift, out):
    """MSB-aligned codes: out = raw >> shift."""
    h, w = out.shape
    for y in prange(h):
        for x in range(w):
            out[y, x] = raw[y, x] >> shift


@njit(cache=True, nogil=True)
def _count_above(raw, top):
    """Number of codes above `top` and the largest code."""
    n = 0
    mx = np.uint16(0)
    h, w = raw.shape
    for y in range(h):
        for x in range(w):
            r = raw[y, x]
            n += np.int64(r > top)
            mx = r if r > mx else mx
    return n, mx


@njit(cache=True, nogil=True)
def _mark_defects(index, state):
    """Defect pixels (flat indices) become DISCARDED (missing; the ATTENUATED bit kept)."""
    w = state.shape[1]
    for k in range(index.shape[0]):
        i = index[k]
        y = i // w
        x = i - y * w
        state[y, x] = (state[y, x] & np.uint8(ATTENUATED)) | np.uint8(DISCARDED)


def codes(raw: np.ndarray, profile: CameraProfile, out: np.ndarray | None = None) -> np.ndarray:
    """The frame as LSB-aligned `bit_depth`-bit codes, uint16 (H, W): packed data (profile.packing; `raw`
    holds the frame's bytes, exactly `profile.frame_bytes()` of them) are unpacked, MSB-aligned words
    shifted down; `raw` itself when it already is such codes. `out`: where to write (else a per-thread
    scratch plane that the next call overwrites). FrameError when `raw` does not fit the profile's format."""
    raw = np.asarray(raw)
    h, w = profile.mask.shape
    src = profile.path.name if profile.path is not None else profile.name
    if profile.packing != "none":
        need = profile.frame_bytes()
        if raw.dtype != np.uint8 or raw.size != need:
            what = f"{raw.nbytes} bytes" if raw.dtype == np.uint8 else f"a {raw.dtype} {raw.shape} array"
            hint = (" (2 bytes per pixel: unpacked 16-bit data; the source sends no "
                    f"{profile.packing}, set the profile's packing to none)" if raw.nbytes == 2 * w * h else "")
            raise FrameError(f"profile {src} says {profile.packing} ({PACKINGS[profile.packing]} bits per pixel): "
                             f"a {w}x{h} frame is {need} bytes, got {what}{hint}")
        data = raw.reshape(-1)
        if out is None:
            out = planes("validity.codes", (h, w), lambda: np.empty((h, w), np.uint16))
        if profile.packing == "mono12packed":
            _unpack_mono12packed_kernel(data, out)
        else:
            _unpack_lsb_kernel(data, PACKINGS[profile.packing], out)
        return out
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise FrameError(f"raw frame must be a 2-D uint16 array, got {raw.dtype} {raw.shape}")
    if raw.shape != (h, w):
        raise FrameError(f"raw frame is {raw.shape[1]}x{raw.shape[0]} but the profile's mask is "
                         f"{profile.width}x{profile.height}")
    if profile.alignment == "msb" and profile.bit_depth < 16:
        if out is None:
            out = planes("validity.codes", (h, w), lambda: np.empty((h, w), np.uint16))
        _shift_kernel(raw, np.uint16(16 - profile.bit_depth), out)
        return out
    if profile.out_of_range == "error" and profile.bit_depth < 16:
        n, mx = _count_above(raw, np.uint16(profile.max_code))
        if n:
            raise FrameError(f"{n} codes above the {profile.bit_depth}-bit range of profile {src} (largest "
                             f"{int(mx)}, at most {profile.max_code}): the data are not {profile.bit_depth}-bit "
                             f"LSB-aligned codes; set the profile's bit_depth, white_level, alignment or packing "
                             f"to what the source sends")
    return raw


def classify(raw: np.ndarray, profile: CameraProfile, mode: str = "threshold", l_min: float | None = None,
             values: np.ndarray | None = None, state: np.ndarray | None = None,
             dark_policy: str = "threshold"):
    """Classify a raw frame (uint16 (H, W), or the frame's bytes for a packed profile: `codes`) into (values
    float32, state uint8), paper 2.3 Eq. 3; defect pixels of the profile become DISCARDED. Output arrays
    may be passed in (e.g. mapped GStreamer memory) and are filled in place. `l_min` overrides the profile's.
    `dark_policy` (mode "threshold" only): "threshold" = the paper's hard l_min (DARK, value = upper
    bound); "weighted" = attenuated pixels between SNR 0 dB and WEIGHTED_LEVEL x l_min become NOISY
    with their measurement, which the reconstruction fuses with its estimate by their noise; below
    SNR 0 dB they stay DARK with l_min x ND as upper bound. A colour profile (profile.cfa): each photosite
    against the same clip code and l_min in its own channel, the best-pixel choice among same-colour
    neighbours (module doc)."""
    if mode not in MODES:
        raise FrameError(f"selection mode must be one of {MODES}, got {mode!r}")
    if dark_policy not in DARK_POLICIES:
        raise FrameError(f"dark policy must be one of {DARK_POLICIES}, got {dark_policy!r}")
    raw = codes(raw, profile)
    if mode == "best" and profile.defect_index.size:
        # a defect is no valid neighbour: its code reads as clipped for the best-pixel choice
        h, w = raw.shape
        c = planes("validity.best_codes", (h, w), lambda: np.empty((h, w), np.uint16))
        np.copyto(c, raw)
        c.reshape(-1)[profile.defect_index] = profile.clip_code
        raw = c
    if values is None:
        values = np.empty(raw.shape, np.float32)
    if state is None:
        state = np.empty(raw.shape, np.uint8)
    s0 = zero_db_signal_dn(profile)
    lm = profile.l_min if l_min is None else float(l_min)
    if not (np.isfinite(lm) and lm >= 0):
        raise FrameError(f"l_min must be a finite number >= 0, got {l_min!r}")
    weighted = mode == "threshold" and dark_policy == "weighted"
    if mode == "threshold":
        dark_att, dark_reg = (lm * WEIGHTED_LEVEL if weighted else lm), -np.inf
    else:
        dark_att, dark_reg = s0, s0
    cfa = getattr(profile, "cfa", cfas.NONE)
    h, w = raw.shape
    chan = cfa_channels(cfa, h, w) if (mode == "best" and cfas.is_colour(cfa)) else _NO_CHANNELS
    _classify_kernel(raw, profile.mask, float(profile.black_level), int(profile.clip_code), float(profile.nd),
                     float(dark_att), float(dark_reg), weighted, mode == "best", float(s0), float(lm), values,
                     state, chan)
    if profile.defect_index.size:
        _mark_defects(profile.defect_index, state)
    return values, state


def noisy_mask(state: np.ndarray) -> np.ndarray:
    """True where the pixel is a NOISY measurement not yet reconstructed."""
    return ((state & REASON_MASK) == NOISY) & ((state & RECONSTRUCTED) == 0)


def default_noise():
    """The default sensor's noise model (gain, read_noise, nd of `CameraProfile`), for frames whose
    profile is unknown."""
    import types
    f = {x.name: x.default for x in CameraProfile.__dataclass_fields__.values()
         if x.name in ("gain", "read_noise", "nd")}
    return types.SimpleNamespace(**f)


def measurement_variance(values, profile, regular=False) -> np.ndarray:
    """Noise variance (linear DN^2) of a measurement at level `values` (ND-scaled linear DN): shot noise
    gain * signal, read noise (gain * read_noise)^2 and quantisation 1/12 (Eq. 4-7), times ND^2 for
    attenuated pixels (their signal is values / ND)."""
    g = float(profile.gain)
    floor = (g * float(profile.read_noise)) ** 2 + 1.0 / 12.0
    v = np.maximum(np.asarray(values, np.float32), 0.0)
    if regular:
        return g * v + floor
    nd = float(profile.nd)
    return nd * g * v + nd * nd * floor


def valid_ratio(state: np.ndarray) -> float:
    """Share of known pixels (paper Fig. 4 / 8b)."""
    return float(np.mean(known_mask(state)))
