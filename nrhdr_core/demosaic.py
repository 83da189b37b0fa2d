"""Joint reconstruction of the missing photosites and the missing colours of a Bayer mosaic under the ND mask
(docs/COLOUR.md "Joint reconstruction").

Green first, then the colour differences (Backes and Froehlich 2020, demosaicing with frequency selective
reconstruction):

1. the green plane from the known green photosites (pull-push, or FSE);
2. at the known red and blue photosites the log colour differences d = log2(max(x, 0) + c) -
   log2(max(G, 0) + c) (a hue is a ratio of channels: across an edge of any contrast the differences stay
   smooth, where linear differences scale with the brightness of an HDR scene); c keeps the logarithm
   finite and noise-tolerant near black (`log_offset`);
3. the differences reconstructed: `preview` on the red and the blue lattice (one cell per 2 x 2 Bayer block:
   the level 1 of the pull-push pyramid with the monochrome preview's neighbour fill), `fse` with presets
   preview, fast, balanced by an FSE image of half size in the linear domain, both turned into ratios 2^d and
   interpolated bilinearly to every photosite; `fse` with a preset of GUIDED_PRESETS (best) at every
   photosite by the FSE guided by the green plane's spectrum (`chroma_fse`: colour detail taken at the
   frequencies green shows, also beyond the lattices' Nyquist limit; aliases of the lattices not; the
   reconstruction about 10 x that of preset fast): R = (max(G, 0) + c) 2^d_R - c, B likewise.
4. the colour-difference median (`_chroma_filter`): the other two channels of each photosite rebuilt from
   its own one and the 3 x 3 medians of the ratios 2^d_R, 2^d_B (Freeman 1988).

The rules of the monochrome chain hold per photosite, for its own channel: known = reason VALID and its value
kept bit for bit; a missing photosite's own channel clamped to its channel's data range [min(known min, 0),
max(known max, its lower bound)] and to its bounds (CLIPPED >= lower, DARK <= upper, `validity.bounds(...,
cfa=)`: the clipped-neighbour rule compares photosites of one colour, computed in vectorised row passes);
NOISY photosites fused with their measurement by `reconstruction.fuse_noisy` on their own Bayer phase
(neighbours of the same colour). The other channels of a photosite stay within their channel's range
[min(known min, 0), max(known max, largest lower bound)], and a channel whose adjacent photosites are all
CLIPPED is at least the smallest of their own-channel values (`_clipped_around`: a saturated region in one
colour). A channel without a known photosite takes its
bounded photosites' bounds as measurements (none either: R = B = G, a grey; green without any: the known
photosites of every channel).
"""
from __future__ import annotations

import warnings

import numpy as np
from numba import get_num_threads, njit, prange

from . import cfa as _cfa
from .fse import f32_key
from .pullpush import (fill_row, pull, pull_level_row, pull_push_levels, pull_row, push,
                       push_row, pyramid, small_levels)
from .scratch import interleaved, planes
from .states import ATTENUATED, CLIPPED, DARK, NOISY, REASON_MASK, RECONSTRUCTED, VALID
from .validity import clip_lower_at_cfa

METHODS = ("preview", "fse")
GUIDED_PRESETS = ("best",)      # fse presets whose colour differences come from the green-guided FSE (step 3)
# offset c of the log colour differences: OFFSET_SHARE x the mean known green level (scales with the data),
# at least OFFSET_NOISE_K sigmas of a regular photosite's noise floor when a noise model is given
OFFSET_SHARE = 2.0 ** -6
OFFSET_NOISE_K = 2.0

# counts of the first pass (`_stats`, per cell row)
_N_MISS, _N_NOISY, _N_BAD, _N_BAD_KNOWN, _N_KNOWN = 0, 1, 2, 3, 4      # _N_KNOWN + ch: known photosites of ch
_N_CLIP = 7                                                            # photosites of reason CLIPPED
_NCNT = 8
# per cell row statistics of the red and blue lattices (`_green`): known min, known max, largest CLIPPED value,
# as order-preserving int32 keys of the floats (`fse.f32_key`)
_F_LO, _F_HI, _F_CLIP = 0, 2, 4                                        # + 0 (red) or 1 (blue)
_NF = 6
_CHUNKS = 64            # row chunks of `_colour` (each with its own row buffers)
_BIG = np.float32(3.0e38)


class DemosaicWarning(UserWarning):
    pass


def reconstruct_cfa(values, state, cfa, method: str = "preview", preset: str = "fast", use_bounds: bool = True,
                    noise=None, fusion: str = "auto", out=None) -> np.ndarray:
    """Planar RGB float32 (3, H, W) from a Bayer mosaic (module docstring): `values` float (H, W), linear
    DN of the channel `cfa` gives each photosite (`cfa.channel_index`); `state` uint8 (H, W)
    (nrhdr_core.states), its RECONSTRUCTED bit set in place where a photosite's own channel was filled.

    method: "preview" (pull-push, fused numba passes; live) or "fse" (FSE with `preset`, one of
    `fse.FSE_PRESETS`); use_bounds: CLIPPED photosites' own channel >= their lower bound, DARK ones' <=
    their upper bound; noise: the noise model (a CameraProfile) NOISY photosites are fused with (`fusion`:
    one of `reconstruction.FUSIONS`; "auto": "fast" for preview, "accurate" for fse), None: they are
    reconstructed like the other missing photosites; out: optional C-contiguous float32 (3, H, W) written
    and returned. Measured photosites keep their value in their own channel, photosites already
    RECONSTRUCTED theirs. Every output value is finite. No photosite known: a DemosaicWarning."""
    name, v32 = _check(values, state, cfa, method, preset, fusion, out)
    from .reconstruction import fusion_for
    fusion = fusion_for(fusion, method)
    h, w = v32.shape
    if out is None:
        out = np.empty((3, h, w), np.float32)
    blk = _cfa.block(name)
    cnt, kg = _first_pass(v32, state, blk, False, use_bounds)
    if cnt[_N_BAD_KNOWN]:
        raise ValueError("reconstruct_cfa: values contain NaN or Inf at known photosites; reconstruction needs "
                         "finite data")
    if cnt[_N_BAD]:
        # non-finite values under missing photosites: they are no measurement and no bound
        return _sanitised(v32, state, name, method, preset, use_bounds, noise, fusion, out)
    known = cnt[_N_KNOWN:_N_KNOWN + 3]
    if known.sum() == 0:
        warnings.warn("reconstruct_cfa: no photosite is known; the bounds stand in for the measurements "
                      "(clipped photosites at their lower bound, too-dark ones at their upper bound, else 0)",
                      DemosaicWarning, stacklevel=2)
    if use_bounds and (known == 0).any():
        lacking = _lacking(state, name, [ch for ch in range(3) if known[ch] == 0])
        if lacking:
            return _with_bounds_as_data(v32, state, name, lacking, method, preset, noise, fusion, out)
    if known[_cfa.G] == 0:
        # no known green photosite: the known photosites of every channel stand in for green
        cnt, kg = _first_pass(v32, state, blk, True, use_bounds)
    chan = planes("demosaic.channels", (name, h, w), lambda: _cfa.channel_index(name, h, w))
    _core(v32, state, chan, blk, kg, cnt, method, preset, bool(use_bounds), noise, fusion, out)
    return out


def _check(values, state, cfa, method, preset, fusion, out):
    """The arguments checked (errors name what is wrong): (cfa name, float32 C-contiguous values)."""
    from .fse import FSE_PRESETS
    from .reconstruction import FUSIONS
    name = _cfa.check(cfa, "reconstruct_cfa: cfa")
    if name == _cfa.NONE:
        raise ValueError("reconstruct_cfa: cfa 'none' is a monochrome sensor (reconstruction.reconstruct_frame)")
    if method not in METHODS:
        raise ValueError(f"reconstruct_cfa: method must be one of {METHODS}, got {method!r}")
    if method == "fse" and preset not in FSE_PRESETS:
        raise ValueError(f"reconstruct_cfa: preset must be one of {tuple(FSE_PRESETS)}, got {preset!r}")
    if fusion not in FUSIONS:
        raise ValueError(f"reconstruct_cfa: noise fusion setting must be one of {FUSIONS}, got {fusion!r}")
    v = np.asarray(values)
    if v.ndim != 2 or v.size == 0:
        raise ValueError(f"reconstruct_cfa: values must be a non-empty 2-D array (H, W), got shape {v.shape}")
    if v.dtype.kind not in "fiu":
        raise ValueError(f"reconstruct_cfa: values must be real numbers, got {v.dtype}")
    if not isinstance(state, np.ndarray) or state.shape != v.shape or state.dtype != np.uint8 \
            or not state.flags.c_contiguous or not state.flags.writeable:
        raise ValueError(f"reconstruct_cfa: state must be a writeable C-contiguous uint8 array of shape {v.shape}, "
                         f"got {getattr(state, 'dtype', type(state))} {np.shape(state)}")
    h, w = v.shape
    if out is not None and (not isinstance(out, np.ndarray) or out.dtype != np.float32 or out.shape != (3, h, w)
                            or not out.flags.c_contiguous or not out.flags.writeable):
        raise ValueError(f"reconstruct_cfa: out must be a writeable C-contiguous float32 array of shape {(3, h, w)}")
    if out is not None and np.shares_memory(out, v):
        raise ValueError("reconstruct_cfa: out must not share memory with values")
    return name, np.ascontiguousarray(v, np.float32)


def _sanitised(v32, state, name, method, preset, use_bounds, noise, fusion, out):
    """A mosaic with non-finite values under missing photosites: those become DISCARDED with value 0 in a
    copy (no measurement, no bound), the copy is reconstructed, the RECONSTRUCTED bits go to `state`."""
    from .states import DISCARDED
    bad = ~np.isfinite(v32)
    v2 = np.where(bad, np.float32(0.0), v32).astype(np.float32)
    s2 = state.copy()
    s2[bad] = (s2[bad] & np.uint8(~REASON_MASK & 0xFF)) | np.uint8(DISCARDED)
    reconstruct_cfa(v2, s2, name, method, preset, use_bounds, noise, fusion, out)
    state |= s2 & np.uint8(RECONSTRUCTED)
    return out


def _bounded(state, idx, channels):
    """bool (H, W): the missing CLIPPED and DARK photosites of `channels`."""
    reason = state & REASON_MASK
    return ((reason == CLIPPED) | (reason == DARK)) & ((state & RECONSTRUCTED) == 0) & np.isin(idx, channels)


def _lacking(state, name, channels):
    """Those of `channels` (without a known photosite) that have a bounded photosite."""
    idx = _cfa.channel_index(name, *state.shape)
    return [ch for ch in channels if _bounded(state, idx, [ch]).any()]


def _with_bounds_as_data(v32, state, name, lacking, method, preset, noise, fusion, out):
    """Channels `lacking` a known photosite: their CLIPPED and DARK photosites count as measured at their
    bound (their own value) in a copy of the state; the RECONSTRUCTED bits go to `state`."""
    bounded = _bounded(state, _cfa.channel_index(name, *state.shape), lacking)
    s2 = state.copy()
    s2[bounded] = s2[bounded] & np.uint8(~REASON_MASK & 0xFF)          # VALID
    reconstruct_cfa(v32, s2, name, method, preset, True, noise, fusion, out)
    _mark(state)
    return out


def log_offset(green_mean: float, noise=None) -> float:
    """c of the log colour differences log2(max(x, 0) + c): OFFSET_SHARE x max(`green_mean`, 0) (the
    mean of the known green values: the top of their pull-push pyramid), at least OFFSET_NOISE_K x the
    noise floor sigma of a regular photosite (gain, read noise and quantisation, Eq. 4-7) when `noise` is
    given; 1 when both are 0."""
    c = OFFSET_SHARE * max(float(green_mean), 0.0)
    if noise is not None:
        g = float(noise.gain)
        c = max(c, OFFSET_NOISE_K * float(np.sqrt(g * g * float(noise.read_noise) ** 2 + 1.0 / 12.0)))
    return float(c) if c > 0.0 else 1.0


def _scratch(h, w):
    """The calling thread's planes for an (h, w) mosaic (`scratch.planes`): green source mask, three
    pull-push pyramids (green, d_R, d_B: values and weights), the lattices' known masks and ratios, row
    buffers of `_colour`, per cell row counts and statistics."""
    def make():
        pv, _, hs, ws, _ = pyramid(h, w)
        n = pv.size
        h1, w1 = int(hs[1]), int(ws[1])
        return dict(kg=np.empty((h, w), np.bool_), pv=np.zeros((3, n), np.float32), pw=np.zeros((3, n), np.float32),
                    kl=np.zeros((2, h1, w1), np.bool_), rl=np.zeros((2, h1, w1), np.float32),
                    rows=np.zeros((_CHUNKS, 4, w), np.float32), ix=np.zeros((_CHUNKS, w), np.int64),
                    keys=np.zeros((h, w), np.float32), mr=np.zeros((_CHUNKS, w), np.float32),
                    fl=np.zeros((3, h, w), np.float32),
                    cnt=np.zeros((h1, _NCNT), np.int64),
                    fst=np.zeros((h1, _NF), np.int32))
    return planes("demosaic.preview", (h, w), make)


def _first_pass(v32, state, blk, g_any, use_bounds):
    """(counts, green source mask) of the mosaic (`_stats`); the green plane's
    pull-push level 1 is pulled in the same pass, and with `use_bounds` the clipped-neighbour keys of the
    cell rows with a CLIPPED photosite (`_clip_keys`). `g_any`: the known photosites of every channel are
    green's sources."""
    h, w = v32.shape
    sc = _scratch(h, w)
    _, _, hs, ws, off = pyramid(h, w)
    deep = hs.shape[0] > 2
    _stats(v32, state, blk, sc["kg"], sc["pv"][0], sc["pw"][0], off[1], ws[1], off[2] if deep else 0,
           ws[2] if deep else 1, deep, sc["cnt"], g_any, bool(use_bounds), sc["keys"])
    return sc["cnt"].sum(axis=0), sc["kg"]


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _stats(values, state, blk, kg, pv, pw, o1, w1, o2, w2, deep, cnt, g_any, with_keys, keys):
    """Per cell row y1 (photosite rows 2 y1, 2 y1 + 1): kg = the known green photosites (`g_any`: every
    known photosite); counts (missing, NOISY, non-finite values, non-finite known values, known photosites
    per channel, CLIPPED photosites); the green plane's pyramid level 1 (`pull_row`) and, `deep`, level 2
    (`pullpush.pull_level_row`, per pair of cell rows); `with_keys`: keys[y] (`_clip_key_row`) of the photosite rows
    of a cell row with a CLIPPED photosite, while they are in cache. Branch-free pixel loops."""
    h, w = values.shape
    h1 = cnt.shape[0]
    zero = np.float32(0.0)
    step = 2 if deep else 1
    for q in prange((h1 + step - 1) // step):
        for y1 in range(step * q, min(step * q + step, h1)):
            _stats_cells(values, state, blk, kg, pv, pw, o1, w1, cnt, g_any, y1, h, w, zero)
            if with_keys and cnt[y1, _N_CLIP] > 0:
                for yy in range(2 * y1, min(2 * y1 + 2, h)):
                    _clip_key_row(values, state, yy, keys[yy])
        if deep:
            pull_level_row(pv, pw, o1, h1, w1, o2, w2, q)


@njit(cache=True, nogil=True, inline="always")
def _stats_cells(values, state, blk, kg, pv, pw, o1, w1, cnt, g_any, y1, h, w, zero):
    """`_stats` of cell row y1."""
    for i in range(_NCNT):
        cnt[y1, i] = 0
    for yy in range(2 * y1, min(2 * y1 + 2, h)):
        cm = 0
        cn = 0
        cb = 0
        cbk = 0
        kn0 = 0
        kn1 = 0
        ccl = 0
        b0 = blk[yy & 1, 0]
        b1 = blk[yy & 1, 1]
        g0 = (b0 == 1) | g_any
        g1 = (b1 == 1) | g_any
        sr = state[yy]                  # row slices: indices from 0 (no wraparound select; the loop vectorises)
        vr = values[yy]
        kr = kg[yy]
        for x in range(w):
            st = sr[x]
            k = (st & REASON_MASK) == VALID
            odd = (x & 1) == 1
            a = vr[x]
            fin = a - a == zero
            cm += np.int64((not k) & ((st & RECONSTRUCTED) == 0))
            cn += np.int64((st & (REASON_MASK | RECONSTRUCTED)) == NOISY)
            cb += np.int64(not fin)
            cbk += np.int64(k & (not fin))
            ccl += np.int64((st & REASON_MASK) == CLIPPED)
            kn0 += np.int64(k & (not odd))
            kn1 += np.int64(k & odd)
            kk = k & (g1 if odd else g0)
            kr[x] = kk
        cnt[y1, _N_MISS] += cm
        cnt[y1, _N_NOISY] += cn
        cnt[y1, _N_BAD] += cb
        cnt[y1, _N_BAD_KNOWN] += cbk
        cnt[y1, _N_CLIP] += ccl
        cnt[y1, _N_KNOWN + b0] += kn0
        cnt[y1, _N_KNOWN + b1] += kn1
    pull_row(values, kg, pv, pw, o1, w1, y1)


def _positions(blk):
    """int64 (3, 2): the (row, column) of each channel's photosite in the 2 x 2 block (green: the first)."""
    pos = np.zeros((3, 2), np.int64)
    for py, px in ((1, 1), (1, 0), (0, 1), (0, 0)):
        pos[int(blk[py, px])] = (py, px)
    return pos


def _core(v32, state, chan, blk, kg, cnt, method, preset, use_bounds, noise, fusion, out):
    """Steps 1-3 of the module docstring and the noise fusion, into `out` (`chan`: the channel plane,
    green sources `kg`, levels 1 and 2 of their pyramid pulled by `_stats`); sets the RECONSTRUCTED bits."""
    h, w = v32.shape
    sc = _scratch(h, w)
    nt = get_num_threads()
    pv, pw, kl, rl = sc["pv"], sc["pw"], sc["kl"], sc["rl"]
    _, _, hs, ws, off = pyramid(h, w)
    pos = _positions(blk)
    h1, w1 = int(hs[1]), int(ws[1])
    deep = hs.shape[0] > 2          # a level above the lattice (frames larger than 2 x 2)
    o2, w2 = (int(off[2]), int(ws[2])) if deep else (int(off[1]), w1)
    # 1. green: its pyramid pulled to the top and pushed back to level 2 (`deep`: `_stats` pulled levels 1
    # and 2, `_green` pushes level 1 row by row); the top: the mean known green level, for the log offset
    if deep:
        pull_push_levels(pv[0], pw[0], hs, ws, off, 2)
    else:
        pull_push_levels(pv[0], pw[0], hs, ws, off)
    top = int(off[hs.shape[0] - 1])
    c = np.float32(log_offset(pv[0][top] / pw[0][top] if pw[0][top] > 0 else 0.0, noise))
    gsrc = np.zeros((1, 1), np.float32)
    fst = sc["fst"]
    noisy = _noisy_phases(v32, state) if noise is not None and cnt[_N_NOISY] else None
    if method != "preview":
        gsrc = _fse_green(v32, state, blk, kg, preset, use_bounds)
    # 2. the green plane under the rules; the log differences on the lattices (level 1 of pyramids 1, 2;
    # `deep`: level 2 pulled)
    crow = _near_clipped(sc["cnt"][:, _N_CLIP], use_bounds, h)
    keys = sc["keys"]
    # the keys of the rows near a CLIPPED photosite; those of the cell rows with one: `_stats`
    _clip_keys(v32, state, crow & ~np.repeat(sc["cnt"][:, _N_CLIP] > 0, 2)[:h], keys)
    _green(v32, state, chan, blk, kg, pv[0], pw[0], off[1], w1, o2, w2, deep, gsrc, method != "preview",
           use_bounds, pos, c, pv[1], pw[1], pv[2], pw[2], kl, fst, sc["ix"], keys, sc["mr"], out[_cfa.G], nt)
    rng = _ranges(fst, cnt)
    # 3. the differences filled on their lattices (as ratios 2^d), bilinear to every photosite, R and B
    lat = [pv[1 + i][off[1]:off[1] + h1 * w1].reshape(h1, w1) for i in range(2)]
    guided = method == "fse" and preset in GUIDED_PRESETS
    if method == "preview":
        if not deep:
            pull_push_levels(pv[1], pw[1], hs, ws, off)
            pull_push_levels(pv[2], pw[2], hs, ws, off)
        _lattice_fill(lat[0], lat[1], kl, pv, pw, hs, ws, off, 2 if deep else hs.shape[0] - 1, o2, w2, rl)
    elif guided:
        dif = _fse_differences(lat, kl, pos, out[_cfa.G], c, rl)
    else:
        for i in range(2):
            _ratio(_fse_lattice(lat[i], kl[i], preset), rl[i])
    ext = np.array([[(h - pos[ch][0] + 1) // 2, (w - pos[ch][1] + 1) // 2] for ch in range(3)], np.int64)
    _colour(v32, state, chan, blk, rl, ext, pos, c, rng, use_bounds, crow, sc["rows"], sc["ix"], keys, sc["mr"], sc["fl"],
            out, not guided, nt)
    if guided:
        _fse_colour(out, dif, pos, c, rng)
    if use_bounds and cnt[_N_CLIP]:
        _clipped_around(state, pos, crow if guided else crow & _lag_edges(h), sc["rows"], sc["fl"], out)
    if noisy is not None:
        _fuse(out, blk, noisy, noise, fusion)
    _chroma_filter(out, state, blk, c, rng, crow, sc["fl"])


def _unkey(key) -> float:
    """The float of an `fse.f32_key` key (the key is an involution of the float's bits)."""
    k = np.array([key], np.int32)
    return float((k ^ ((k >> 31) & 0x7FFFFFFF)).view(np.float32)[0])


def _ranges(fst, cnt):
    """float32 (3, 3): per channel [min(known min, 0), known max, max(known max, largest CLIPPED value)]
    from the keys `fst`; a channel without a known photosite is not clamped (its values come from green)."""
    r = np.empty((3, 3), np.float32)
    r[:, 0] = -_BIG
    r[:, 1:] = _BIG
    for i, ch in enumerate((_cfa.R, _cfa.B)):
        if cnt[_N_KNOWN + ch] > 0:
            hi = _unkey(fst[:, _F_HI + i].max())
            cl = fst[:, _F_CLIP + i].max()
            top = hi if cl == -0x7FFFFFFF - 1 else max(hi, _unkey(cl))
            r[ch] = (min(_unkey(fst[:, _F_LO + i].min()), 0.0), hi, top)
    return r


@njit(cache=True, nogil=True, inline="always")
def _clip_key_of(st, v):
    """The term in the clipped-neighbour rule of a photosite of state `st` and value `v`: +inf not attenuated
    (no term), its value (a lower bound) attenuated and CLIPPED, -inf attenuated and not CLIPPED (the rule
    does not hold). Branch-free."""
    att = (st & ATTENUATED) != 0
    cl = (st & REASON_MASK) == CLIPPED
    e = np.float32(-np.inf) if att else np.float32(np.inf)
    return v if (att & cl) else e


@njit(cache=True, nogil=True, inline="always")
def _clip_key(values, state, y, x):
    """`_clip_key_of` photosite (y, x)."""
    return _clip_key_of(state[y, x], values[y, x])


@njit(cache=True, nogil=True, inline="always")
def _clip_rule_at(values, state, chan, y, x, green):
    """The clipped-neighbour rule of `validity.bounds(..., cfa=)` at photosite (y, x)
    (`validity.clip_lower_at_cfa`): the minimum of `_clip_key` over the same-colour photosites of its
    5 x 5 window in the frame (red, blue: their Bayer phase's 3 x 3; green (`green`): its phase's 3 x 3 and
    the 4 diagonal neighbours): -inf (one attenuated and not CLIPPED): NaN, no rule; +inf (no attenuated
    one): `clip_lower_at_cfa` (the 9 x 9 window: rare); else the smallest lower bound. Branch-free inside
    the frame's border of 2."""
    h, w = state.shape
    inf = np.float32(np.inf)
    m = inf
    if (y >= 2) & (y + 2 < h) & (x >= 2) & (x + 2 < w):
        for dy in (-2, 0, 2):
            for dx in (-2, 0, 2):
                m = min(m, _clip_key(values, state, y + dy, x + dx))
        if green:
            for dy in (-1, 1):
                for dx in (-1, 1):
                    m = min(m, _clip_key(values, state, y + dy, x + dx))
    else:
        for yy in range(max(y - 2, y & 1), min(y + 3, h), 2):
            for xx in range(max(x - 2, x & 1), min(x + 3, w), 2):
                m = min(m, _clip_key(values, state, yy, xx))
        if green:
            for yy in (y - 1, y + 1):
                for xx in (x - 1, x + 1):
                    if (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w):
                        m = min(m, _clip_key(values, state, yy, xx))
    if m == inf:
        return clip_lower_at_cfa(values, state, chan, y, x, h, w)
    return m if m > -inf else np.float32(np.nan)


@njit(cache=True, nogil=True, inline="always")
def _clip_key_row(values, state, y, k):
    """k = `_clip_key` of row y's photosites, the even columns first, then the odd ones from (w + 1) // 2 on
    (each Bayer phase's keys contiguous, for `_clip_rule_row`)."""
    w = state.shape[1]
    wa = (w + 1) // 2
    sr = state[y]                   # row slices: a 2-D index does not vectorise
    vr = values[y]
    ko = k[wa:]
    for j in range(wa):
        k[j] = _clip_key_of(sr[2 * j], vr[2 * j])
    for j in range(w // 2):
        ko[j] = _clip_key_of(sr[2 * j + 1], vr[2 * j + 1])


@njit(cache=True, nogil=True, parallel=True)
def _clip_keys(values, state, crow, keys):
    """keys[y] (`_clip_key_row`) in the rows `crow`."""
    for y in prange(state.shape[0]):
        if crow[y]:
            _clip_key_row(values, state, y, keys[y])


@njit(cache=True, nogil=True, inline="always")
def _clip_rule_row(keys, y, x0, green, m):
    """m[j] = the minimum of `_clip_rule_at` over the window of photosite x0 + 2 j of row y, for the
    photosites of that phase not at the row's ends (1 <= j < n - 1), from the phase-split `keys`
    (`_clip_keys`; rows beyond the frame replicated: a repeated row leaves a minimum as it is); contiguous
    branch-free loops over row slices (they vectorise; a 2-D index does not)."""
    h, w = keys.shape
    wa = (w + 1) // 2
    n = (w - x0 + 1) // 2
    b = x0 * wa
    ka = keys[y - 2 if y >= 2 else y, b:b + n]
    k0 = keys[y, b:b + n]
    kb = keys[y + 2 if y + 2 < h else y, b:b + n]
    for j in range(1, n - 1):
        t = min(min(ka[j - 1], ka[j]), ka[j + 1])
        t = min(t, min(min(k0[j - 1], k0[j]), k0[j + 1]))
        m[j] = min(t, min(min(kb[j - 1], kb[j]), kb[j + 1]))
    if green and h > 1:
        ob = (1 - x0) * wa + x0 - 1      # the diagonal neighbours: the other phase's j - 1 + x0 and j + x0
        ku = keys[y - 1 if y >= 1 else y + 1, ob:ob + n]
        kd = keys[y + 1 if y + 1 < h else y - 1, ob:ob + n]
        for j in range(1, n - 1):
            d = min(min(ku[j], ku[j + 1]), min(kd[j], kd[j + 1]))
            m[j] = min(m[j], d)


@njit(cache=True, nogil=True, inline="always")
def _own_row(o, values, state, chan, y, x0, hi, use_bounds, green, keys, ix, mr):
    """The photosites x0, x0 + 2, ... of row y, whose own channel's estimate is o[x]: measured (VALID) or
    already RECONSTRUCTED: their value; missing: at most max(hi, lower bound), then within their bounds
    (CLIPPED: >= lower bound, DARK: <= the value), and the RECONSTRUCTED bit. Branch-free over the whole
    row (it vectorises). The missing CLIPPED regular photosites get their bit in a second loop, only in
    rows that have one (compacted through the index buffer `ix`), where the clipped-neighbour rule
    (`_clip_rule_row` from the phase-split `keys` into the row buffer `mr`, `_clip_rule_at` at the row's
    ends; `chan`: the channel plane; `green`: the green photosites' window) raises their lower bound l to l'
    (max(min(a, max(hi, l')), l') of the first result is the clamp with l')."""
    w = values.shape[1]
    x0 = x0 & 1                     # provably >= 0: numba's loops indexed from it vectorise (no wraparound)
    big = _BIG
    flag = np.uint8(RECONSTRUCTED)
    sr = state[y]
    vr = values[y]
    ncr = 0
    for x in range(w):
        st = sr[x]
        r = st & REASON_MASK
        v = vr[x]
        own = (x & 1) == x0
        keep = (r == VALID) | ((st & RECONSTRUCTED) != 0)
        lb = v if (use_bounds & (r == CLIPPED)) else -big
        ub = v if (use_bounds & (r == DARK)) else big
        t = hi if hi > lb else lb
        a = o[x]
        b = t if a > t else a
        b = lb if lb > b else b
        b = ub if ub < b else b
        b = v if keep else b
        o[x] = b if own else a
        cr = own & ((st & (ATTENUATED | REASON_MASK | RECONSTRUCTED)) == CLIPPED)
        sr[x] = st | (flag * np.uint8(own & (not keep) & (not cr)))
        ncr += np.int64(cr)
    if ncr > 0:
        n = 0
        for x in range(x0, w, 2):       # the missing CLIPPED regular photosites, compacted (branch-free)
            ix[n] = x
            n += 1 if (sr[x] & (ATTENUATED | REASON_MASK | RECONSTRUCTED)) == CLIPPED else 0
        if use_bounds:
            _clip_rule_row(keys, y, x0, green, mr)
        nj = (w - x0 + 1) // 2
        inf = np.float32(np.inf)
        nan = np.float32(np.nan)
        for q in range(n):
            x = ix[q]
            j = (x - x0) >> 1
            t = mr[j]
            m = t if t > -inf else nan          # a select (-inf: an attenuated neighbour not CLIPPED, at random)
            if not (use_bounds & (j >= 1) & (j < nj - 1) & (t < inf)):
                # rare: no rule, the row's ends, no attenuated photosite in the window (+inf)
                m = nan
                if use_bounds and 1 <= j < nj - 1:
                    m = clip_lower_at_cfa(values, state, chan, y, x, values.shape[0], w)
                elif use_bounds:
                    m = _clip_rule_at(values, state, chan, y, x, green)
            ok = (m == m) & (m > vr[x])
            t = hi if hi > m else m
            a = o[x]
            b = t if a > t else a
            b = m if m > b else b
            o[x] = b if ok else a
            sr[x] = sr[x] | flag


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _green(values, state, chan, blk, kg, pv, pw, o1, w1, o2, w2, deep, gsrc, from_src, use_bounds, pos, c, pvr, pwr,
           pvb, pwb, kl, fst, ixs, keys, mrs, gout, nt):
    """Per cell row: the green plane into `gout` (the pull-push fill `pullpush.fill_row` of the
    green sources `kg`, or `gsrc` with `from_src`; a convex combination of known values, so only the
    missing green photosites' bounds apply, `_own_row`); then at the cell's red and blue photosites the log
    colour differences (weight 1 where known, else 0) into level 1 of the d_R and d_B pyramids and `kl`,
    and the lattices' statistics `fst` (keys of the known min and max and the largest CLIPPED value;
    integer reductions vectorise, float ones do not). The logarithm only at
    the known cells (compacted through the index buffers `ixs`, one per chunk of cell rows). `deep` (the
    pyramids have a level 2, at o2, w2 wide): green's level 1 is pushed from its level 2 (`pullpush.push_row`) row
    by row before the fill reads it, and level 2 of d_R and d_B is pulled (`pullpush.pull_level_row`) per pair of cell
    rows. Chunks interleaved over the `nt` threads (`scratch.interleaved`)."""
    h, w = values.shape
    h1 = (h + 1) // 2
    nch = ixs.shape[0]
    step = 2 if deep else 1
    n2 = (h1 + step - 1) // step
    per = (nch + nt - 1) // nt
    for i in prange(per * nt):
        kc = interleaved(i, per, nt)
        if kc >= nch:
            continue
        ix = ixs[kc]
        for q in range(kc * n2 // nch, (kc + 1) * n2 // nch):
            for y1 in range(step * q, min(step * q + step, h1)):
                if deep and not from_src:
                    push_row(pv, pw, o1, w1, o2, w2, y1)
                _green_cells(values, state, chan, blk, kg, pv, o1, w1, gsrc, from_src, use_bounds, pos, c, pvr,
                             pwr, pvb, pwb, kl, fst, ix, keys, mrs[kc], gout, y1)
            if deep:
                pull_level_row(pvr, pwr, o1, h1, w1, o2, w2, q)
                pull_level_row(pvb, pwb, o1, h1, w1, o2, w2, q)


@njit(cache=True, nogil=True, inline="always")
def _green_cells(values, state, chan, blk, kg, pv, o1, w1, gsrc, from_src, use_bounds, pos, c, pvr, pwr, pvb, pwb,
                 kl, fst, ix, keys, mr, gout, y1):
    """`_green` of cell row y1 (index buffer `ix`; `ix`, `keys`, row buffer `mr`: `_own_row`'s)."""
    h, w = values.shape
    zero = np.float32(0.0)
    one = np.float32(1.0)
    big = _BIG
    kmax = np.int32(0x7FFFFFFF)
    kmin = np.int32(-0x7FFFFFFF - 1)
    vi = values.view(np.int32)
    for y in range(2 * y1, min(2 * y1 + 2, h)):
        g = gout[y]
        if from_src:
            for x in range(w):
                g[x] = gsrc[y, x]
        else:
            fill_row(values, kg, pv, o1, w1, y, g, True)
        _own_row(g, values, state, chan, y, 0 if blk[y & 1, 0] == 1 else 1, big, use_bounds, True, keys, ix, mr)
    base = o1 + y1 * w1
    for i in range(2):
        ch = 0 if i == 0 else 2
        y = 2 * y1 + pos[ch, 0]
        px = pos[ch, 1] & 1                         # provably >= 0 (as `_own_row`'s x0)
        pvd = pvr if i == 0 else pvb
        pwd = pwr if i == 0 else pwb
        lo = kmax
        hi = kmin
        cl = kmin
        n = 0 if y >= h else (w - px + 1) // 2      # the lattice's cells in the frame
        yr = min(y, h - 1)                          # row slices (a 2-D index does not vectorise)
        sr = state[yr]
        vir = vi[yr]
        vr = values[yr]
        gr = gout[yr]
        pvs = pvd[base:base + w1]
        pws = pwd[base:base + w1]
        klr = kl[i, y1]
        for x1 in range(n):
            x = 2 * x1 + px
            r = sr[x] & REASON_MASK
            k = r == VALID
            key = f32_key(vir[x])
            lo = min(lo, key if k else kmax)
            hi = max(hi, key if k else kmin)
            cl = max(cl, key if (r == CLIPPED) else kmin)
            pvs[x1] = zero
            pws[x1] = one if k else zero
            klr[x1] = k
        nk = 0
        for x1 in range(n):                         # compaction apart: the loop above vectorises
            ix[nk] = x1
            nk += 1 if klr[x1] else 0
        for q in range(nk):
            x1 = ix[q]
            x = 2 * x1 + px
            a = vr[x]
            gv = gr[x]
            a = (a if a > zero else zero) + c
            gv = (gv if gv > zero else zero) + c
            pvs[x1] = np.log2(a / gv)
        for x1 in range(n, w1):
            pvs[x1] = zero
            pws[x1] = zero
            klr[x1] = False
        fst[y1, _F_LO + i] = lo
        fst[y1, _F_HI + i] = hi
        fst[y1, _F_CLIP + i] = cl


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _lattice_fill(lat0, lat1, known, pv, pw, hs, ws, off, first, o2, w2, ratio):
    """The two difference lattices (level 1 of the pyramids pv[1], pv[2]; levels up to `first` pulled):
    their pyramids pulled from level `first` to the top and pushed back to it (one pyramid per thread,
    `pullpush.small_levels`), then each cell its value where known, else the weighted mean of its known
    8-neighbours, else its parent's pushed value (level 2 at o2, w2 wide: `pullpush.fill_row`, as
    the monochrome preview fills level 0); stored as the ratio 2^d."""
    levels = hs.shape[0] - 1
    for i in prange(2):
        small_levels(pv[1 + i], pw[1 + i], hs, ws, off, first, levels)
    h1 = known.shape[1]
    for q in prange(2 * h1):
        i = q // h1
        y = q - i * h1
        r = ratio[i, y]
        fill_row(lat0 if i == 0 else lat1, known[i], pv[1 + i], o2, w2, y, r, True)
        for j in range(r.shape[0]):
            r[j] = np.exp2(r[j])


@njit(cache=True, nogil=True, parallel=True)
def _ratio(lat, ratio):
    """ratio = 2^lat."""
    for i in prange(lat.shape[0]):
        for j in range(lat.shape[1]):
            ratio[i, j] = np.exp2(lat[i, j])


@njit(cache=True, nogil=True, inline="always")
def _expand(lat, i0, i1, a, px, ext_w, w, buf, e):
    """buf[x] (x < w) = the lattice row pair (i0, i1; weight a of i1) bilinear at photosite column x, for a
    lattice of columns px, px + 2, ... (ext_w of them; edge values replicated; none: its first cell's);
    e: a row buffer (the lattice row pair's blend, then interleaved with the means of neighbours: loops
    that vectorise)."""
    px = px & 1                     # provably >= 0 (as `_own_row`'s x0)
    b = np.float32(1.0) - a
    l0 = lat[i0]
    l1 = lat[i1]
    half = np.float32(0.5)
    if ext_w < 1:                   # no column of the lattice in the frame: its first cell's value everywhere
        e0 = b * l0[0] + a * l1[0]
        for x in range(w):
            buf[x] = e0
        return
    for j in range(ext_w):
        e[j] = b * l0[j] + a * l1[j]
    for j in range(ext_w - 1):
        buf[px + 2 * j] = e[j]
        buf[px + 2 * j + 1] = half * (e[j] + e[j + 1])
    last = px + 2 * (ext_w - 1)
    el = e[ext_w - 1]
    buf[last] = el
    if px == 1:
        buf[0] = e[0]
    for x in range(last + 1, w):
        buf[x] = el


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _colour(values, state, chan, blk, rl, ext, pos, c, rng, use_bounds, crow, rows, ixs, keys, mrs, fl, out, lag, nt):
    """R and B at every photosite, row by row in chunks (row buffers `rows`): (max(G, 0) + c) x the ratio
    2^d bilinear on its lattice (`rl`; `ext`: the lattices' real extents per channel) - c, within the
    channel's range; the red and blue photosites' own channel by `_own_row`. In the rows `crow` (near a
    CLIPPED photosite) first green, then red and blue from their own row, at least the smallest own value
    of their adjacent CLIPPED photosites (`_clipped_around`; the other rows' neighbours there; the bounds
    into `fl`). `lag`: then `_clipped_around` of the chunk's inner rows too, one row behind (`_clipped_row`
    of row y - 1 once row y is done; the chunk's first and last rows: `_lag_edges`). `keys`, `ixs`, `mrs`:
    `_own_row`'s (buffers per chunk). Chunks interleaved over the `nt` threads (`scratch.interleaved`)."""
    h, w = values.shape
    zero = np.float32(0.0)
    half = np.float32(0.5)
    nch = rows.shape[0]
    per = (nch + nt - 1) // nt
    for ic in prange(per * nt):
        k = interleaved(ic, per, nt)
        if k >= nch:
            continue
        ya = k * h // nch
        for y in range(ya, (k + 1) * h // nch):
            g = out[1, y]
            near = crow[y]
            if near:
                gx = pos[1, 1] if (y & 1) == pos[1, 0] else 1 - pos[1, 1]
                _lift_row(g, out[1], state, y, 1 - gx, True, True, False, rows[k, 2], rows[k, 3], True, fl[1, y])
            for i in range(2):
                ch = 0 if i == 0 else 2
                eh = ext[ch, 0]
                buf = rows[k, i]
                t = y - pos[ch, 0]
                i0 = 0 if t < 0 else min(t >> 1, eh - 1)
                a = half if (t > 0 and (t & 1) == 1 and i0 + 1 < eh) else zero
                _expand(rl[i], i0, min(i0 + 1, eh - 1), a, pos[ch, 1], ext[ch, 1], w, buf, rows[k, 2])
                lo = rng[ch, 0]
                top = rng[ch, 2]
                o = out[ch, y]
                for x in range(w):
                    gv = g[x]
                    e = ((gv if gv > zero else zero) + c) * buf[x] - c
                    e = e if e - e == zero else top
                    e = lo if e < lo else e
                    o[x] = top if e > top else e
                if pos[ch, 0] == (y & 1):
                    _own_row(o, values, state, chan, y, pos[ch, 1], rng[ch, 1], use_bounds, False, keys, ixs[k], mrs[k])
                    if near:
                        _lift_row(o, out[ch], state, y, 1 - pos[ch, 1], True, False, False, rows[k, 2], rows[k, 3],
                                  True, fl[ch, y])
            if lag and y - 1 > ya and crow[y - 1]:
                _clipped_row(state, pos, out, y - 1, rows[k, 2], rows[k, 3], fl)


@njit(cache=True, nogil=True, inline="always")
def _cv(own, state, x):
    """own[x] where the photosite is CLIPPED (`state`: its row), else -_BIG (a minimum with it lifts nothing)."""
    return own[x] if (state[x] & REASON_MASK) == CLIPPED else -_BIG


@njit(cache=True, nogil=True)
def _lift_row(o, own, state, y, x0, hz, vt, dg, b0, b1, fresh, fl):
    """o[x] (x = x0, x0 + 2, ...) at least the smallest own-channel value `own` of its neighbours in the
    frame (`hz`: (y, x -+ 1), `vt`: (y -+ 1, x), `dg`: (y -+ 1, x -+ 1)) when they are all CLIPPED: a
    neighbour not CLIPPED counts -_BIG, one outside the frame +_BIG. b0, b1: row buffers (the column
    minima of rows y -+ 1 and row y's values, in branch-free loops that vectorise; computed with `fresh`,
    else those of the previous call in the same row and channel). fl[x]: the bound found (< _BIG: one
    applies), for `_rebuild_row`. The row's interior in one contiguous loop over every column: the other
    columns of `o` and `fl` are stored back with the bits they hold."""
    x0 = x0 & 1                     # provably >= 0 (as `_own_row`'s x0)
    h, w = state.shape
    big = _BIG
    up = y - 1 if y > 0 else y
    dn = y + 1 if y + 1 < h else y
    bu = np.float32(-big) if y > 0 else big          # + a value: the row's own, or +_BIG outside
    bd = np.float32(-big) if y + 1 < h else big
    if fresh and (vt or dg):
        ou = own[up]                                 # row slices: a 2-D index does not vectorise
        su = state[up]
        od = own[dn]
        sd = state[dn]
        for x in range(w):
            a = _cv(ou, su, x)
            a = a if bu < 0 else big
            c = _cv(od, sd, x)
            c = c if bd < 0 else big
            b0[x] = min(a, c)
    if fresh and hz:
        oy = own[y]
        sy = state[y]
        for x in range(w):
            b1[x] = _cv(oy, sy, x)
    for x in range(1, w - 1):       # the interior, every column (a select keeps the other parity): it vectorises
        m = big
        m = min(m, min(b1[x - 1], b1[x + 1])) if hz else m
        m = min(m, b0[x]) if vt else m
        m = min(m, min(b0[x - 1], b0[x + 1])) if dg else m
        on = (x & 1) == x0
        v = o[x]
        o[x] = m if (on & (m > v) & (m < big)) else v
        fl[x] = m if on else fl[x]
    for x in (0, w - 1):            # the row's ends (the same column twice when w == 1: a lift is idempotent)
        if (x & 1) != x0:
            continue
        m = big
        xl = x - 1 if x > 0 else x
        xr = x + 1 if x + 1 < w else x
        if hz:
            m = min(m, min(b1[xl] if x > 0 else big, b1[xr] if x + 1 < w else big))
        if vt:
            m = min(m, b0[x])
        if dg:
            m = min(m, min(b0[xl] if x > 0 else big, b0[xr] if x + 1 < w else big))
        v = o[x]
        o[x] = m if ((m > v) & (m < big)) else v
        fl[x] = m


@njit(cache=True, nogil=True)
def _clipped_row(state, pos, out, y, b0, b1, fl):
    """`_clipped_around` in row y: red and blue outside their own rows (the neighbours in the rows above
    and below; green and the own rows' neighbours: `_colour`)."""
    y = np.int64(y)
    for ch in (0, 2):
        o = out[ch, y]
        px = pos[ch, 1]
        if (y & 1) != pos[ch, 0]:
            _lift_row(o, out[ch], state, y, px, False, True, False, b0, b1, True, fl[ch, y])
            _lift_row(o, out[ch], state, y, 1 - px, False, False, True, b0, b1, False, fl[ch, y])


@njit(cache=True, nogil=True, parallel=True)
def _clipped_around(state, pos, crow, rows, fl, out):
    """A channel at a photosite of another colour whose adjacent photosites of that channel (green: the 4
    neighbours; red, blue: the 2 in its row or column, else the 4 diagonal ones) are all CLIPPED: at least
    the smallest of their own-channel values (each at least its lower bound), so that a saturated region
    comes out in one saturated colour. Only the rows `crow` (`_near_clipped`); row buffers `rows`, one
    pair per chunk of rows; the bounds into `fl`."""
    h = state.shape[0]
    nch = rows.shape[0]
    for k in prange(nch):
        for y in range(k * h // nch, (k + 1) * h // nch):
            if crow[y]:
                _clipped_row(state, pos, out, y, rows[k, 0], rows[k, 1], fl)


def _near_clipped(ccnt, use_bounds, h):
    """bool (h,): the photosite rows of a cell row with a CLIPPED photosite in it or in a cell row beside
    it (`ccnt`: CLIPPED counts per cell row); all False without `use_bounds`."""
    c = (ccnt > 0) & bool(use_bounds)
    d = c.copy()
    d[1:] |= c[:-1]
    d[:-1] |= c[1:]
    return np.ascontiguousarray(np.repeat(d, 2)[:h])


def _lag_edges(h):
    """bool (h,): the first and the last row of each chunk of `_colour`, whose `_clipped_around` needs a row
    of the chunk beside it (the other rows: `_colour` with `lag`)."""
    def make():
        e = np.zeros(h, np.bool_)
        for k in range(_CHUNKS):
            y0, y1 = k * h // _CHUNKS, (k + 1) * h // _CHUNKS
            if y1 > y0:
                e[y0] = e[y1 - 1] = True
        return e
    return planes("demosaic.lag_edges", (h,), make)


@njit(cache=True, nogil=True, parallel=True)
def _mark_kernel(state):
    h, w = state.shape
    flag = np.uint8(RECONSTRUCTED)
    for y in prange(h):
        for x in range(w):
            st = state[y, x]
            m = ((st & REASON_MASK) != VALID) & ((st & RECONSTRUCTED) == 0)
            state[y, x] = st | (flag * np.uint8(m))


def _mark(state):
    """RECONSTRUCTED on every missing photosite (reason not VALID, not yet RECONSTRUCTED)."""
    _mark_kernel(state)


def _fse_green(v32, state, blk, kg, preset, use_bounds):
    """The green plane by FSE (`fse.fse_reconstruct`) from the green sources `kg`, with the missing green
    photosites' bounds, clamped to [min(known min, 0), max(known max, largest lower bound)]."""
    from .fse import fse_reconstruct
    h, w = v32.shape
    if not kg.any():
        return np.zeros((h, w), np.float32)
    own = np.zeros((h, w), bool)
    for py in range(2):
        for px in range(2):
            own[py::2, px::2] = blk[py, px] == _cfa.G
    lower = upper = None
    miss = ~kg & ((state & RECONSTRUCTED) == 0) & own
    if use_bounds:
        reason = state & REASON_MASK
        lower = np.where(miss & (reason == CLIPPED), v32, np.nan).astype(np.float32)
        upper = np.where(miss & (reason == DARK), v32, np.nan).astype(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        res = fse_reconstruct(v32, kg, lower, upper, preset)
    kv = v32[kg]
    top = float(kv.max())
    if lower is not None and not np.isnan(lower).all():
        top = max(top, float(np.nanmax(lower)))
    np.nan_to_num(res, copy=False, nan=0.0, posinf=top, neginf=0.0)
    np.clip(res, min(float(kv.min()), 0.0), top, out=res)
    return res


def _fse_lattice(lat, known, preset):
    """A difference lattice filled by FSE in the linear domain (the differences are logarithms already)."""
    from .reconstruction import reconstruct
    if not known.any():
        return np.zeros(lat.shape, np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.ascontiguousarray(reconstruct(lat, known, method="fse", preset=preset, domain="linear"),
                                    np.float32)


def _noisy_phases(v32, state):
    """Per Bayer phase (py, px): its (values, known mask, NOISY-not-yet-RECONSTRUCTED mask) as planes
    (`_phase_split`, the calling thread's scratch), or None where it has no such NOISY photosite."""
    h, w = state.shape
    hp, wp = (h + 1) // 2, (w + 1) // 2

    def make():
        return (np.empty((2, 2, hp, wp), np.float32), np.empty((2, 2, hp, wp), np.bool_),
                np.empty((2, 2, hp, wp), np.bool_), np.empty((hp, 2, 2), np.int64))
    pv, pk, pn, rc = planes("demosaic.phases", (h, w), make)
    _phase_split(v32, state, pv, pk, pn, rc)
    cnt = rc.sum(axis=0)
    res = {}
    for py in range(2):
        for px in range(2):
            sl = (py, px, slice(0, (h - py + 1) // 2), slice(0, (w - px + 1) // 2))
            res[py, px] = (pv[sl], pk[sl], pn[sl]) if cnt[py, px] else None
    return res


@njit(cache=True, nogil=True, parallel=True)
def _phase_split(values, state, pv, pk, pn, rc):
    """pv[py, px], pk[py, px], pn[py, px] = the values, the known mask and the NOISY-not-RECONSTRUCTED mask
    of the Bayer phase (py, px) (one pass over the mosaic); rc[y2, py, px] = the count of those NOISY
    photosites in its row y2."""
    h, w = values.shape
    n1 = w // 2
    for y2 in prange(pv.shape[2]):
        for py in range(2):
            y = 2 * y2 + py
            for px in range(2):
                rc[y2, py, px] = 0
            if y >= h:
                continue
            vr = values[y]                  # row slices, both phases in one loop (it vectorises)
            sr = state[y]
            v0, v1 = pv[py, 0, y2], pv[py, 1, y2]
            k0, k1 = pk[py, 0, y2], pk[py, 1, y2]
            z0, z1 = pn[py, 0, y2], pn[py, 1, y2]
            c0 = 0
            c1 = 0
            for x2 in range(n1):
                sa = sr[2 * x2]
                sb = sr[2 * x2 + 1]
                na = (sa & (REASON_MASK | RECONSTRUCTED)) == NOISY
                nb = (sb & (REASON_MASK | RECONSTRUCTED)) == NOISY
                v0[x2] = vr[2 * x2]
                v1[x2] = vr[2 * x2 + 1]
                k0[x2] = (sa & REASON_MASK) == VALID
                k1[x2] = (sb & REASON_MASK) == VALID
                z0[x2] = na
                z1[x2] = nb
                c0 += np.int64(na)
                c1 += np.int64(nb)
            if w % 2:                       # the last column: phase 0
                sa = sr[w - 1]
                na = (sa & (REASON_MASK | RECONSTRUCTED)) == NOISY
                v0[n1] = vr[w - 1]
                k0[n1] = (sa & REASON_MASK) == VALID
                z0[n1] = na
                c0 += np.int64(na)
            rc[y2, py, 0] = c0
            rc[y2, py, 1] = c1


def _fuse(out, blk, noisy, noise, fusion):
    """NOISY photosites: their own channel fused with their measurement (`reconstruction.fuse_noisy`) on
    each Bayer phase apart (neighbours of the same colour; `noisy`: `_noisy_phases`); the fused value
    replaces the estimate."""
    from .reconstruction import fuse_noisy
    for (py, px), m in noisy.items():
        if m is not None:
            fuse_noisy(out[int(blk[py, px])][py::2, px::2], m[0], m[1], m[2], noise, setting=fusion)


def warmup() -> None:
    """Compile (or load from numba's cache) the kernels of both methods, on a tiny synthetic mosaic (writeable
    and read-only values, NOISY photosites fused, clipped and dark ones bounded), and the parallel pyramid
    levels of large frames."""
    from .validity import default_noise
    rng = np.random.default_rng(0)
    h, w = 16, 20
    vals = rng.uniform(10.0, 1000.0, (h, w)).astype(np.float32)
    st = np.where(rng.random((h, w)) < 0.3, np.uint8(NOISY), np.uint8(VALID)).astype(np.uint8)
    st[0, :3] = CLIPPED
    st[1, :3] = DARK | ATTENUATED
    ro = vals.copy()
    ro.flags.writeable = False          # mapped input buffers are read-only: numba compiles them apart
    for method in METHODS:
        for v in (vals, ro):
            reconstruct_cfa(v, st.copy(), "rggb", method=method, preset="fast", noise=default_noise())
    # the pyramid levels pulled and pushed in parallel (`pullpush.pull_push_levels`: levels of
    # `pullpush.SERIAL_LEVEL` cells or more)
    _, _, hs, ws, off = pyramid(h, w)
    pv = np.zeros((3, off[-1]), np.float32)
    pw = np.zeros((3, off[-1]), np.float32)
    pull(pv[0], pw[0], off[1], hs[1], ws[1], off[2], hs[2], ws[2])
    push(pv[0], pw[0], off[1], hs[1], ws[1], off[2], ws[2])


# ---- colour-difference median (docs/COLOUR.md "Colour-difference median") ---------------------------------
# Freeman's median of colour differences (US patent 4,724,395, 1988; the log-domain form: the median of the
# ratio (x + c) / (G + c) is 2^ of the median of the log difference, the logarithm being monotonic), 3 x 3, once,
# after the colour pass and the noise fusion: each photosite keeps its own channel and takes the other two
# from it and the medians of the ratios R : G and B : G around it.

_CM_LO, _CM_MI, _CM_HI, _CM_MR, _CM_MB = 6, 7, 8, 9, 10     # row buffers after the ratio ring (0-5)
_CM_ROWS = 11


def _chroma_scratch(h, w):
    """The calling thread's planes of the colour-difference median (`scratch.planes`): per chunk of rows a
    ring of three ratio rows per difference and row buffers (`_CM_*`), the ratio rows beside each chunk
    (`bnd`: the row above and the row below) and the green plane's range per row."""
    def make():
        return dict(rows=np.zeros((_CHUNKS, _CM_ROWS, w), np.float32),
                    bnd=np.zeros((_CHUNKS, 2, 2, w), np.float32), gmm=np.zeros((h, 2), np.float32),
                    gk=np.zeros((h, 3), np.int64))
    return planes("demosaic.chroma", (h, w), make)


@njit(cache=True, nogil=True, inline="always")
def _ratio_row(out, y, c, dr, db):
    """dr, db = the ratios (max(R, 0) + c) / (max(G, 0) + c) and likewise for B in row y of `out`."""
    zero = np.float32(0.0)
    one = np.float32(1.0)
    r = out[0, y]
    g = out[1, y]
    b = out[2, y]
    for x in range(r.shape[0]):
        gv = g[x]
        rv = r[x]
        bv = b[x]
        q = one / ((gv if gv > zero else zero) + c)
        dr[x] = ((rv if rv > zero else zero) + c) * q
        db[x] = ((bv if bv > zero else zero) + c) * q


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _chroma_edges(out, c, bnd, gmm, gk, keyed):
    """Before any row changes: `bnd[k]` = the ratio rows just above and just below chunk k of `_chroma_median`
    (edge rows replicated) and per row y of green: `keyed`: gk[y] = the `fse.f32_key` keys of its min and
    max and its count of -0 (integer reductions vectorise), else gmm[y] = (min, max) (`_green_range`)."""
    h = out.shape[1]
    nch = bnd.shape[0]
    gi = out[1].view(np.int32)
    kmax = np.int32(0x7FFFFFFF)
    kmin = np.int32(-0x7FFFFFFF - 1)
    for k in prange(nch):
        y0 = k * h // nch
        y1 = (k + 1) * h // nch
        if y1 > y0:
            ya = y0 - 1 if y0 > 0 else y0
            yb = y1 if y1 < h else h - 1
            _ratio_row(out, ya, c, bnd[k, 0, 0], bnd[k, 0, 1])
            _ratio_row(out, yb, c, bnd[k, 1, 0], bnd[k, 1, 1])
        for y in range(y0, y1):
            if keyed:
                r = gi[y]
                klo = kmax
                khi = kmin
                nz = 0
                for x in range(r.shape[0]):
                    key = f32_key(r[x])
                    klo = min(klo, key)
                    khi = max(khi, key)
                    nz += np.int64(r[x] == kmin)            # the bits of -0
                gk[y, 0] = klo
                gk[y, 1] = khi
                gk[y, 2] = nz
                continue
            g = out[1, y]
            lo = _BIG
            hi = -_BIG
            for x in range(g.shape[0]):
                lo = min(lo, g[x])
                hi = max(hi, g[x])
            gmm[y, 0] = lo
            gmm[y, 1] = hi


@njit(cache=True, nogil=True, inline="always")
def _sort3(a, b, c):
    """(a, b, c) in ascending order."""
    lo = min(a, b)
    hi = max(a, b)
    return min(lo, c), max(lo, min(hi, c)), max(hi, c)


@njit(cache=True, nogil=True, inline="always")
def _med3(a, b, c):
    """The median of three values."""
    return max(min(a, b), min(max(a, b), c))


@njit(cache=True, nogil=True)
def _median3_row(a, b, c, lo, mi, hi, m):
    """m[x] = the median of the 3 x 3 window of the rows a, b, c around column x (edge columns replicated):
    each column sorted, then the median of the largest low, the median of the middles and the smallest high
    (exact for 9 values)."""
    w = a.shape[0]
    for x in range(w):
        lo[x], mi[x], hi[x] = _sort3(a[x], b[x], c[x])
    for x in range(1, w - 1):
        m[x] = _med3(max(max(lo[x - 1], lo[x]), lo[x + 1]), _med3(mi[x - 1], mi[x], mi[x + 1]),
                     min(min(hi[x - 1], hi[x]), hi[x + 1]))
    for x in (0, w - 1):
        xl = x - 1 if x > 0 else x
        xr = x + 1 if x + 1 < w else x
        m[x] = _med3(max(max(lo[xl], lo[x]), lo[xr]), _med3(mi[xl], mi[x], mi[xr]),
                     min(min(hi[xl], hi[x]), hi[xr]))


@njit(cache=True, nogil=True, inline="always")
def _floored(m, v):
    """v lifted to the clipped-neighbour lower bound m where one applies (m < _BIG)."""
    return m if ((m > v) & (m < _BIG)) else v


@njit(cache=True, nogil=True, inline="always")
def _rebuild_row(g, s, t, ms, mt, gp, c, glo, ghi, slo, shi, tlo, thi, fg, fs, ft, floor):
    """A row of green photosites (columns of parity gp) and photosites of one other colour s (t: the third
    channel; ms, mt: their median ratios), each rebuilt from its own channel a: with A = (max(a, 0) + c) / q
    (q = 1 at green, ms at s) green = A - c, s = A ms - c, t = A mt - c where not its own, within
    [lo, hi] (a non-finite result: hi); with `floor` each rebuilt value then at least its clipped-neighbour
    lower bound (fg, fs, ft: the bounds `_lift_row` found for the same photosites and channels, `_floored`).
    Contiguous and branch-free (it vectorises)."""
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for x in range(g.shape[0]):
        isg = (x & 1) == gp
        g0 = g[x]
        s0 = s[x]
        a = g0 if isg else s0
        q = one if isg else ms[x]
        gc = ((a if a > zero else zero) + c) / q
        eg = gc - c
        es = gc * ms[x] - c
        et = gc * mt[x] - c
        eg = eg if eg - eg == zero else ghi
        es = es if es - es == zero else shi
        et = et if et - et == zero else thi
        eg = min(max(eg, glo), ghi)
        es = min(max(es, slo), shi)
        et = min(max(et, tlo), thi)
        if floor:
            eg = _floored(fg[x], eg)
            es = _floored(fs[x], es)
            et = _floored(ft[x], et)
        g[x] = g0 if isg else eg
        s[x] = es if isg else s0
        t[x] = et


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _chroma_median(out, blk, c, lim, bnd, crow, fl, rows):
    """Row by row in chunks: the 3 x 3 medians of the ratios R : G and B : G (a ring of three ratio rows per
    chunk, read from rows not yet changed; the rows beside the chunk from `bnd`), then each photosite's other
    two channels from its own one (`_rebuild_row`; `lim`: (lo, hi) per channel), in the rows `crow` each at
    least the clipped-neighbour lower bound `fl` that `_colour` and `_clipped_around` found for it (they
    depend on own channels only, which stay as they are)."""
    h = out.shape[1]
    nch = rows.shape[0]
    rlo, rhi, glo, ghi, blo, bhi = lim[0, 0], lim[0, 1], lim[1, 0], lim[1, 1], lim[2, 0], lim[2, 1]
    for k in prange(nch):
        buf = rows[k]
        y0 = k * h // nch
        y1 = (k + 1) * h // nch
        if y1 <= y0:
            continue
        for i in range(2):
            buf[i] = bnd[k, 0, i]                   # ring slot of row y0 - 1
        _ratio_row(out, y0, c, buf[2], buf[3])      # slot of row y0
        s0, s1, s2 = 0, 2, 4                         # ring slots of rows y - 1, y, y + 1
        for y in range(y0, y1):
            if y + 1 < y1:
                _ratio_row(out, y + 1, c, buf[s2], buf[s2 + 1])
            else:
                for i in range(2):
                    buf[s2 + i] = bnd[k, 1, i]
            for i in range(2):
                _median3_row(buf[s0 + i], buf[s1 + i], buf[s2 + i], buf[_CM_LO], buf[_CM_MI], buf[_CM_HI],
                             buf[_CM_MR + i])
            gp = 0 if blk[y & 1, 0] == 1 else 1
            red = blk[y & 1, 1 - gp] == 0               # the row's other colour
            a, b = (0, 2) if red else (2, 0)
            ms, mt = (buf[_CM_MR], buf[_CM_MB]) if red else (buf[_CM_MB], buf[_CM_MR])
            slo, shi, tlo, thi = (rlo, rhi, blo, bhi) if red else (blo, bhi, rlo, rhi)
            # the flag as a constant in each call: the inlined loop compiles without the floors where none apply
            if crow[y]:
                _rebuild_row(out[1, y], out[a, y], out[b, y], ms, mt, gp, c, glo, ghi, slo, shi, tlo, thi,
                             fl[1, y], fl[a, y], fl[b, y], True)
            else:
                _rebuild_row(out[1, y], out[a, y], out[b, y], ms, mt, gp, c, glo, ghi, slo, shi, tlo, thi,
                             fl[1, y], fl[a, y], fl[b, y], False)
            s0, s1, s2 = s1, s2, s0


def _green_range(out, c, sc):
    """(min, max) of the green plane as floats, each row's taken from +-_BIG on (`_chroma_edges`, which fills
    the chunks' edge ratio rows `sc["bnd"]` too): from the keys where the plane holds no -0 and its extremes
    lie within +-_BIG (there equal keys are equal floats), else by float comparisons (the first of equal
    values kept)."""
    gk = sc["gk"]
    _chroma_edges(out, c, sc["bnd"], sc["gmm"], gk, True)
    lo, hi = _unkey(gk[:, 0].min()), _unkey(gk[:, 1].max())
    if not gk[:, 2].any() and -_BIG < lo < _BIG and -_BIG < hi < _BIG:
        return lo, hi
    _chroma_edges(out, c, sc["bnd"], sc["gmm"], gk, False)
    return float(sc["gmm"][:, 0].min()), float(sc["gmm"][:, 1].max())


def _chroma_filter(out, state, blk, c, rng, crow, fl):
    """The colour-difference median (the block comment above) on the finished `out`: own channels untouched
    (measured photosites bit for bit, fused NOISY ones, bounded ones), the other channels within their
    channel's range (`rng`: R, B as `_colour`; green within the green plane's range), the clipped-neighbour
    lower bounds `fl` (`_lift_row`) in the rows `crow` (`_near_clipped`) again."""
    h, w = state.shape
    sc = _chroma_scratch(h, w)
    c = np.float32(c)
    lim = np.empty((3, 2), np.float32)
    lim[:, 0] = rng[:, 0]
    lim[:, 1] = rng[:, 2]
    lo, hi = _green_range(out, c, sc)
    lim[_cfa.G] = (min(lo, 0.0), hi)
    _chroma_median(out, blk, c, lim, sc["bnd"], crow, fl, sc["rows"])


# ---- green-guided colour differences of the fse method (docs/COLOUR.md "False colour") ---------------------

def _fse_differences(lat, kl, pos, g, c, rl):
    """float32 (2, H, W): the log differences d_R, d_B (`lat`, known where `kl`, on their lattices) at every
    photosite by the green-guided FSE (`chroma_fse.guided_fse`, both channels in one pass, guide
    log2(max(G, 0) + c)); `rl` (the lattices' ratios for `_colour`) = 2^d at the lattice cells."""
    from .chroma_fse import guided_fse
    h, w = g.shape
    sc = planes("demosaic.fse_colour", (h, w), lambda: dict(
        guide=np.empty((h, w), np.float32), dif=np.empty((2, h, w), np.float32),
        full=np.empty((2, h, w), np.float32), known=np.empty((2, h, w), np.bool_)))
    guide, dif, full, known = sc["guide"], sc["dif"], sc["full"], sc["known"]
    np.log2(np.maximum(g, 0.0) + c, out=guide)
    full[:] = 0.0
    known[:] = False
    par = [(int(pos[ch][0]), int(pos[ch][1])) for ch in (_cfa.R, _cfa.B)]
    for i, (py, px) in enumerate(par):
        hl, wl = full[i, py::2, px::2].shape
        full[i, py::2, px::2] = lat[i][:hl, :wl]
        known[i, py::2, px::2] = kl[i][:hl, :wl]
    guided_fse(full, known, guide, [p[0] for p in par], [p[1] for p in par], dif)
    for i, (py, px) in enumerate(par):
        hl, wl = full[i, py::2, px::2].shape
        rl[i][:hl, :wl] = np.exp2(dif[i][py::2, px::2])
    return dif


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _fse_colour(out, dif, pos, c, rng):
    """R and B at the photosites of the other colours: (max(G, 0) + c) 2^d - c (`dif`: d_R, d_B at every
    photosite), within the channel's range (`rng` as `_colour`); their own photosites stay as `_colour` left
    them."""
    h, w = out.shape[1], out.shape[2]
    zero = np.float32(0.0)
    for y in prange(h):
        for i in range(2):
            ch = 0 if i == 0 else 2
            own_row = (y & 1) == pos[ch, 0]
            lo = rng[ch, 0]
            top = rng[ch, 2]
            for x in range(w):
                if own_row and (x & 1) == pos[ch, 1]:
                    continue
                gv = out[1, y, x]
                e = ((gv if gv > zero else zero) + c) * np.exp2(dif[i, y, x]) - c
                e = e if e - e == zero else top
                e = lo if e < lo else e
                out[ch, y, x] = top if e > top else e
