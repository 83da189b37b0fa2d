"""Temporal reconstruction: the previous output, aligned by a fast motion estimate, as a prior for the
missing pixels and as extra measurements for the measured and noisy ones, where a per-block consistency
check against the noise model trusts it (docs/TEMPORAL.md).

Anchors: recursive multi-frame frequency selective reconstruction (Jonscher et al., PCS 2016) and
consistency-checked multi-frame reconstruction for a fixed non-regular mask (arXiv 2203.09200); the
recursive, variance-weighted averaging is a motion-compensated recursive (Kalman-type) temporal filter.

Per frame (`TemporalReconstructor.process`):

1. known mask and bounds (`validity.prepare`);
2. global motion from integral projections of the log2 values of the measured pixels (rows and
   columns, this frame's against the previous frame's), integer search and a parabolic sub-pixel fit,
   then refined by 2-D matching of the measured pixels against the previous output nearby;
3. per block (``block`` x ``block``) and candidate motion (none, the global shift) the consistency of
   the frame's measured pixels with the aligned previous output: z = (m - p)^2 / (var_m + var_p +
   (tol p)^2), var_m the measurement's noise (Eq. 4-7 as `validity.measurement_variance`), var_p the
   previous output's variance; the block is trusted when the mean of min(z, Z_OUT) stays below
   ``z_mean`` and few pixels are outliers (z > Z_OUT); most blocks untrusted = a scene cut: the state is
   reset and the frame is reconstructed alone (`reconstruction.reconstruct_frame`, the same bits);
4. in trusted blocks measured pixels are averaged with their aligned past by inverse variance (per pixel:
   an outlier restarts its pixel); missing pixels whose past is already averaged over ``reuse_frames``
   reconstructions take it as a known value (the block costs nothing: FSE skips blocks with nothing
   missing), the others are reconstructed from the averaged values and fused with their past;
5. untrusted blocks (motion the candidates do not explain, occlusion, a block with an outlier) are
   reconstructed alone.

The state (the previous output and its per-pixel variance) belongs to the instance: one per stream;
`reset` on a seek, flush or caps change.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .scratch import planes
from .states import ATTENUATED, CLIPPED, DARK, NOISY, REASON_MASK, RECONSTRUCTED, VALID

# block decisions
FRESH = 0      # no trusted past: reconstructed alone
REFRESH = 1    # trusted: measured pixels averaged, missing ones reconstructed and fused with their past
REUSE = 2      # trusted and the past of every missing pixel settled: missing pixels keep their past
NO_PRIOR = 3   # trusted measurements but an outlier: measured pixels averaged per pixel, missing ones alone
NO_EVIDENCE = 4  # too few measured pixels to judge: reconstructed alone, not counted for a cut

SNAP = 0.1            # pixels: a global shift this close to an integer is taken as that integer
Z_OUT = 16.0          # z beyond this (4 sigma) is an outlier: its pixel restarts, its block keeps no prior
DEFAULTS = dict(
    block=16,          # decision block (pixels)
    search=32,         # global motion search range (pixels)
    z_mean=2.5,        # a block is consistent when its mean clipped z is below this
    outliers=0.02,     # ... and at most this share (at least 1 pixel) of its measured pixels are outliers
    tol=0.02,          # relative model tolerance of the aligned past (interpolation, slow light changes)
    shift_error=0.35,  # pixels: position error of a moving candidate (its variance x the squared gradient)
    cut_share=0.5,     # more untrusted blocks than this share (of blocks with evidence) = a scene cut
    max_frames=16,     # the recursive average of a measured pixel weighs its past at most this many frames
    reuse_frames=4,    # missing pixels whose past averages this many reconstructions are reused as known
    rec_noise=1.0,     # variance of a fresh reconstruction in units of a regular pixel's noise at its level
    rec_tol=0.03,      # ... plus (rec_tol x level)^2: the model error averaging does not remove
    min_evidence=8,    # measured pixels a block needs to be judged
)


class TemporalReconstructor:
    """`reconstruction.reconstruct_frame` with a temporal prior (module docstring; docs/TEMPORAL.md).

    method, preset, use_bounds, fusion: as `reconstruct_frame` (method may be a callable
    f(missing_share) -> (method, preset), as `nrreconstruct method=auto` passes); options: DEFAULTS."""

    def __init__(self, method="fse", preset="fast", use_bounds=True, fusion="auto", **options):
        from .reconstruction import FUSIONS, METHODS
        if not callable(method) and method not in METHODS:
            raise ValueError(f"temporal reconstruction: method must be one of {METHODS}, got {method!r}")
        if fusion not in FUSIONS:
            raise ValueError(f"temporal reconstruction: fusion must be one of {FUSIONS}, got {fusion!r}")
        bad = sorted(set(options) - set(DEFAULTS))
        if bad:
            raise TypeError(f"temporal reconstruction: unknown option {bad[0]!r}; known: {sorted(DEFAULTS)}")
        o = dict(DEFAULTS, **options)
        for k in ("block", "search", "max_frames", "reuse_frames", "min_evidence"):
            if not (isinstance(o[k], (int, np.integer)) and not isinstance(o[k], bool) and o[k] >= 1):
                raise ValueError(f"temporal reconstruction: option {k} must be an integer >= 1, got {o[k]!r}")
        for k in ("z_mean", "outliers", "tol", "shift_error", "cut_share", "rec_noise", "rec_tol"):
            if not (isinstance(o[k], (int, float)) and math.isfinite(o[k]) and o[k] >= 0):
                raise ValueError(f"temporal reconstruction: option {k} must be a finite number >= 0, got {o[k]!r}")
        self.method, self.preset, self.use_bounds, self.fusion = method, preset, bool(use_bounds), fusion
        self.options = o
        self._prev = self._var = self._sig = None
        self.frames = 0          # frames since the last reset

    def reset(self) -> None:
        """Forget the past: the next frame is reconstructed alone."""
        self._prev = self._var = self._sig = None
        self.frames = 0

    # ---- one frame ------------------------------------------------------------------------------------
    def process(self, values: np.ndarray, state: np.ndarray, noise=None) -> dict:
        """Reconstruct the frame in place (float32 values, uint8 states, C-contiguous, as
        `reconstruct_frame`) with the temporal prior; measured pixels of trusted blocks are replaced by
        their recursive average. `noise`: the noise model (gain, read_noise, nd: a CameraProfile; None =
        the default sensor's). Returns the work done: "missing" (pixels filled, as `reconstruct_frame`
        returns), "blocks", the shares "fresh", "refreshed", "reused", "no_prior", "no_evidence" of the
        blocks, "motion" (dy, dx): the motion most trusted blocks took (the global estimate where none), "cut" and "reset" (True when the frame was
        reconstructed alone)."""
        from . import reconstruction, validity
        o = self.options
        if not (isinstance(values, np.ndarray) and values.ndim == 2 and values.dtype == np.float32
                and values.flags.c_contiguous and values.flags.writeable):
            raise ValueError("temporal reconstruction: values must be a writeable C-contiguous float32 (H, W) "
                             "array")
        if not (isinstance(state, np.ndarray) and state.dtype == np.uint8 and state.shape == values.shape
                and state.flags.c_contiguous and state.flags.writeable):
            raise ValueError(f"temporal reconstruction: state must be a writeable C-contiguous uint8 array of "
                             f"shape {values.shape}")
        if noise is None:
            noise = validity.default_noise()
        h, w = values.shape
        bs = int(o["block"])
        nby, nbx = (h + bs - 1) // bs, (w + bs - 1) // bs
        report = {"missing": 0, "blocks": nby * nbx, "fresh": 1.0, "refreshed": 0.0, "reused": 0.0,
                  "no_prior": 0.0, "no_evidence": 0.0, "motion": (0.0, 0.0), "cut": False, "reset": True}
        if self._prev is not None and self._prev.shape != values.shape:
            self.reset()
        known, lower, upper, work, pv, pvar, dec, cand = _planes(h, w, nby, nbx)
        n_miss, n_unknown, known, lower, upper = validity._prepare(
            values, state, known, lower if self.use_bounds else None, upper if self.use_bounds else None,
            self.use_bounds)
        method, preset = self.method, self.preset
        if callable(method):
            method, preset = method(n_miss / float(h * w)) if n_miss else ("preview", preset)
        g = np.float32(noise.gain)
        floor = np.float32(float(noise.gain) ** 2 * float(noise.read_noise) ** 2 + 1.0 / 12.0)
        nd = np.float32(noise.nd)
        sig = projections(values, state)
        if self._prev is None or n_miss != n_unknown or not _finite(values):
            # first frame (or a frame the general path must judge: non-finite values, pixels filled upstream)
            return self._alone(values, state, noise, method, preset, report, g, floor, nd, sig)
        # 2. global motion
        dy, dx = refine_motion(values, state, self._prev, *global_motion(sig, self._sig, int(o["search"])))
        # 3. per-block consistency
        lo_a = lower if lower is not None else _EMPTY
        cy, cx = _candidates(dy, dx)
        _judge_blocks(values, state, self._prev, self._var, cy, cx, bs, dec, cand,
                      g, floor, nd, np.float32(o["z_mean"]), np.float32(o["outliers"]), np.float32(o["tol"]),
                      np.float32(Z_OUT), int(o["min_evidence"]), np.float32(o["rec_noise"]),
                      np.float32(o["rec_tol"]), np.float32(o["reuse_frames"]), np.float32(o["shift_error"]) ** 2)
        counts = np.bincount(dec.ravel(), minlength=5)
        trusted = (dec == REFRESH) | (dec == REUSE) | (dec == NO_PRIOR)
        # the dominant motion: the candidate most trusted blocks took (the global estimate when none did)
        top = int(np.argmax(np.bincount(cand[trusted], minlength=cy.size))) if trusted.any() else -1
        report["motion"] = (float(cy[top]), float(cx[top])) if top >= 0 else (float(dy), float(dx))
        judged = dec.size - counts[NO_EVIDENCE]
        untrusted = counts[FRESH]
        if judged and untrusted > float(o["cut_share"]) * judged:
            report["cut"] = True
            return self._alone(values, state, noise, method, preset, report, g, floor, nd, sig)
        # 4. measured pixels averaged, settled missing pixels reused, the rest marked for the reconstruction
        up_a = upper if upper is not None else _EMPTY
        _prepare_work(values, state, self._prev, self._var, cy, cx, bs, dec, cand,
                      known, lo_a, up_a, lower is not None, work, pv, pvar, g, floor, nd, np.float32(o["tol"]),
                      np.float32(Z_OUT), np.float32(o["max_frames"]), np.float32(o["shift_error"]) ** 2)
        noisy = None
        if _any_noisy_missing(state, known):
            noisy = ((state & (REASON_MASK | RECONSTRUCTED)) == NOISY) & ~known
        reconstruction.reconstruct(work, known, method=method, preset=preset, lower=lower, upper=upper,
                                   out=work, noisy=noisy, noise=noise if noisy is not None else None,
                                   fusion=self.fusion)
        # 5. fused with the past, written back, kept as the next frame's past
        n = _finish(values, state, work, pv, pvar, self._prev, self._var, lo_a, up_a, lower is not None,
                    g, np.float32(o["rec_noise"]), np.float32(o["rec_tol"]), np.float32(o["reuse_frames"]),
                    floor)
        self.frames += 1
        self._sig = sig
        tot = float(dec.size)
        report.update(missing=int(n), reset=False, fresh=counts[FRESH] / tot, refreshed=counts[REFRESH] / tot,
                      reused=counts[REUSE] / tot, no_prior=counts[NO_PRIOR] / tot,
                      no_evidence=counts[NO_EVIDENCE] / tot)
        return report

    def _alone(self, values, state, noise, method, preset, report, g, floor, nd, sig) -> dict:
        """The frame reconstructed alone (`reconstruct_frame`, the same bits); the state restarts from it."""
        from . import reconstruction
        report["missing"] = int(reconstruction.reconstruct_frame(
            values, state, method=method, preset=preset, use_bounds=self.use_bounds, noise=noise,
            fusion=self.fusion))
        if self._prev is None or self._prev.shape != values.shape:
            self._prev = np.empty_like(values)
            self._var = np.empty_like(values)
        o = self.options
        _restart(values, state, self._prev, self._var, g, floor, nd, np.float32(o["rec_noise"]),
                 np.float32(o["rec_tol"]))
        self.frames = 1
        self._sig = sig
        return report


_EMPTY = np.full((1, 1), np.nan, np.float32)


def _planes(h, w, nby, nbx):
    """The calling thread's working planes: known, lower, upper, work, aligned past and its variance,
    block decisions and candidates."""
    return planes("temporal.work", (h, w, nby, nbx), lambda: (
        np.empty((h, w), np.bool_), np.empty((h, w), np.float32), np.empty((h, w), np.float32),
        np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w), np.float32),
        np.empty((nby, nbx), np.uint8), np.empty((nby, nbx), np.uint8)))


# ---- noise model --------------------------------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _meas_var(level, attenuated, g, floor, nd):
    """Noise variance of a measurement at `level` (ND-scaled DN), Eq. 4-7 (`validity.measurement_variance`)."""
    m = level if level > 0 else np.float32(0.0)
    if attenuated:
        return nd * g * m + nd * nd * floor
    return g * m + floor


@njit(cache=True, nogil=True, inline="always")
def _rec_var(level, g, floor, rec_noise, rec_tol):
    """Variance assigned to a fresh reconstruction at `level`."""
    m = level if level > 0 else np.float32(0.0)
    return rec_noise * (g * m + floor) + (rec_tol * m) * (rec_tol * m)


@njit(cache=True, nogil=True, parallel=True)
def _restart(values, state, prev, var, g, floor, nd, rec_noise, rec_tol):
    """The past after a frame reconstructed alone: its output, measured pixels with their noise variance,
    the others with a fresh reconstruction's."""
    h, w = values.shape
    for y in prange(h):
        for x in range(w):
            v = values[y, x]
            st = state[y, x]
            prev[y, x] = v
            if (st & REASON_MASK) == VALID:
                var[y, x] = _meas_var(v, (st & ATTENUATED) != 0, g, floor, nd)
            else:
                var[y, x] = _rec_var(v, g, floor, rec_noise, rec_tol)


@njit(cache=True, nogil=True, parallel=True)
def _finite_kernel(values):
    h, w = values.shape
    bad = 0
    for y in prange(h):
        b = 0
        for x in range(w):
            a = values[y, x]
            b += np.int64(not (a - a == np.float32(0.0)))
        bad += b
    return bad


def _finite(values) -> bool:
    return _finite_kernel(values) == 0


@njit(cache=True, nogil=True, parallel=True)
def _any_noisy_kernel(state, known):
    h, w = state.shape
    n = 0
    for y in prange(h):
        c = 0
        for x in range(w):
            c += np.int64(((state[y, x] & (REASON_MASK | RECONSTRUCTED)) == NOISY) & (not known[y, x]))
        n += c
    return n


def _any_noisy_missing(state, known) -> bool:
    return _any_noisy_kernel(state, known) > 0


# ---- global motion: integral projections of log2 values -------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _log2f(bits):
    """log2 of a float32 from its bits (exponent + linear mantissa; within 0.09 stops), values below 1 as 1."""
    one = np.int32(0x3F800000)
    b = bits if bits > one else one
    return np.float32(b - one) * np.float32(1.0 / 8388608.0)


@njit(cache=True, nogil=True, parallel=True)
def _projections(values, state, rs, rn, cs, cn):
    """Row and column sums of log2 over the measured (VALID) pixels, and their counts: rows (rs, rn);
    columns per chunk of rows (cs, cn: (chunks, W)), summed by the caller."""
    h, w = values.shape
    vi = values.view(np.int32)
    nch = cs.shape[0]
    for ch in prange(nch):
        for x in range(w):
            cs[ch, x] = 0.0
            cn[ch, x] = 0.0
        for y in range(ch * h // nch, (ch + 1) * h // nch):
            sr = np.float32(0.0)
            nr = np.float32(0.0)
            for x in range(w):
                kf = np.float32(1.0) if (state[y, x] & REASON_MASK) == VALID else np.float32(0.0)
                lv = kf * _log2f(vi[y, x])
                sr += lv
                nr += kf
                cs[ch, x] += lv
                cn[ch, x] += kf
            rs[y] = sr
            rn[y] = nr


def projections(values, state):
    """The frame's motion signature: mean log2 of the measured pixels per row and per column, and their
    counts ((rows, row counts), (columns, column counts), float64). Each frame's own measured pixels:
    the fixed mask samples both frames alike, so it does not bias the match."""
    h, w = values.shape
    nch = max(1, min(h, 16))
    rs, rn, cs, cn = planes("temporal.projections", (h, w, nch), lambda: (
        np.empty(h, np.float32), np.empty(h, np.float32), np.empty((nch, w), np.float32),
        np.empty((nch, w), np.float32)))
    _projections(values, state, rs, rn, cs, cn)
    rn64 = rn.astype(np.float64)
    cn64 = cn.sum(axis=0, dtype=np.float64)
    return ((rs / np.maximum(rn64, 1.0), rn64), (cs.sum(axis=0, dtype=np.float64) / np.maximum(cn64, 1.0), cn64))


@njit(cache=True, nogil=True)
def _shift_1d(a, na, b, nb, r):
    """Shift d (|d| <= r, sub-pixel) with a[x] ~ b[x - d] (profiles of means, na / nb samples per line): the
    mean absolute difference over the overlap where both lines hold at least a quarter of their median
    count, minimised on integers, refined by a parabola. 0 when no shift leaves a third of the lines."""
    n = a.shape[0]
    r = min(r, n // 3)
    lim = 0.25 * np.median(na)
    cost = np.full(2 * r + 1, np.inf)
    for i in range(2 * r + 1):
        d = i - r
        s = 0.0
        c = 0
        for x in range(max(0, d), min(n, n + d)):
            if na[x] > lim and nb[x - d] > lim:
                s += abs(a[x] - b[x - d])
                c += 1
        if c >= n // 3 and c > 0:
            cost[i] = s / c
    best = r
    for i in range(2 * r + 1):
        if cost[i] < cost[best]:
            best = i
    if not cost[best] < np.inf:
        return 0.0
    f = 0.0
    if 0 < best < 2 * r:
        cm, c0, cq = cost[best - 1], cost[best], cost[best + 1]
        den = cm - 2.0 * c0 + cq
        if den > 0 and cm < np.inf and cq < np.inf:
            f = 0.5 * (cm - cq) / den
            f = min(max(f, -0.5), 0.5)
    return (best - r) + f


def global_motion(cur, past, search: int = 32):
    """(dy, dx) of the frame whose `projections` are `cur` against the one of `past`: content at (y, x)
    of the frame was at (y - dy, x - dx); integer search within `search` pixels, parabolic sub-pixel fit
    (`_shift_1d`), snapped to an integer within SNAP."""
    (ra, rna), (ca, cna) = cur
    (rb, rnb), (cb, cnb) = past
    dy = _shift_1d(ra, rna, rb, rnb, int(search))
    dx = _shift_1d(ca, cna, cb, cnb, int(search))
    return _snap(dy), _snap(dx)


REFINE_RADIUS = 2     # pixels: the 2-D refinement searches this far around the projections' estimate
REFINE_STEP = 3       # ... on every REFINE_STEP-th row and column


@njit(cache=True, nogil=True, parallel=True)
def _match_costs(values, state, prev, oy, ox, rad, step, cost):
    """cost[i, j] = mean min(|log2 frame - log2 past|, 1) over the measured pixels of every step-th row
    and column, the past shifted by (oy + i - rad, ox + j - rad) (pixels outside it not counted)."""
    h, w = values.shape
    vi = values.view(np.int32)
    pi = prev.view(np.int32)
    n = 2 * rad + 1
    for k in prange(n * n):
        sy = oy + k // n - rad
        sx = ox + k % n - rad
        s = 0.0
        c = 0
        for y in range(max(sy, 0), min(h, h + sy), step):
            for x in range(max(sx, 0), min(w, w + sx), step):
                if (state[y, x] & REASON_MASK) != VALID:
                    continue
                d = abs(_log2f(vi[y, x]) - _log2f(pi[y - sy, x - sx]))
                s += d if d < 1.0 else 1.0
                c += 1
        cost[k // n, k % n] = s / c if c > 16 else np.inf


def refine_motion(values, state, prev, dy: float, dx: float):
    """(dy, dx) refined by 2-D matching of the frame's measured pixels against the past's log2 values
    around the rounded estimate (`_match_costs`, REFINE_RADIUS, REFINE_STEP): the best whole-pixel shift and
    a parabolic sub-pixel fit along each axis, snapped to an integer within SNAP. Integral projections
    confuse the axes of a small or one-directional scene; this settles them."""
    rad = REFINE_RADIUS
    n = 2 * rad + 1
    cost = planes("temporal.match", n, lambda: np.empty((n, n), np.float64))
    oy, ox = int(round(dy)), int(round(dx))
    _match_costs(values, state, prev, oy, ox, rad, REFINE_STEP, cost)
    if not np.isfinite(cost).any():
        return dy, dx
    i, j = np.unravel_index(int(np.argmin(cost)), cost.shape)

    def fit(a, b, c):
        den = a - 2.0 * b + c
        return float(min(max(0.5 * (a - c) / den, -0.5), 0.5)) if den > 0 and np.isfinite(a + c) else 0.0

    fy = fit(cost[i - 1, j], cost[i, j], cost[i + 1, j]) if 0 < i < n - 1 else 0.0
    fx = fit(cost[i, j - 1], cost[i, j], cost[i, j + 1]) if 0 < j < n - 1 else 0.0
    return _snap(oy + i - rad + fy), _snap(ox + j - rad + fx)


def _snap(d: float) -> float:
    """A shift within SNAP of an integer is that integer (no interpolation blur for a still camera)."""
    r = round(d)
    return float(r) if abs(d - r) < SNAP else float(d)


def _candidates(dy: float, dx: float):
    """The motions a block may take, in the order of preference (float32 arrays cy, cx): none, the global
    motion rounded to whole pixels (no interpolation), the global motion."""
    out = [(0.0, 0.0)]
    for c in ((float(round(dy)), float(round(dx))), (dy, dx)):
        if c not in out:
            out.append(c)
    a = np.array(out, np.float32)
    return np.ascontiguousarray(a[:, 0]), np.ascontiguousarray(a[:, 1])


# ---- the aligned past ----------------------------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _aligned(prev, var, y, x, sy, sx, h, w, mis2):
    """(value, variance) of the past at (y - sy, x - sx), bilinear; variance inf outside the frame. A
    moving candidate adds the uncertainty of its alignment: mis2 (its position error squared, pixels^2)
    x the squared local gradient; a sub-pixel position the interpolation's: (local range / 2)^2 x
    4 f (1 - f)."""
    fy = np.float32(y) - sy
    fx = np.float32(x) - sx
    if fy < 0 or fx < 0 or fy > h - 1 or fx > w - 1:
        return np.float32(0.0), np.float32(np.inf)
    y0 = int(fy)
    x0 = int(fx)
    ty = fy - np.float32(y0)
    tx = fx - np.float32(x0)
    y1 = min(y0 + 1, h - 1)
    x1 = min(x0 + 1, w - 1)
    a = prev[y0, x0]
    extra = np.float32(0.0)
    if mis2 > 0:
        gx = prev[y0, x1] - prev[y0, max(x0 - 1, 0)]
        gy = prev[y1, x0] - prev[max(y0 - 1, 0), x0]
        extra = mis2 * np.float32(0.25) * (gx * gx + gy * gy)
    if ty == 0 and tx == 0:
        return a, var[y0, x0] + extra
    b, c, d = prev[y0, x1], prev[y1, x0], prev[y1, x1]
    wa = (1 - ty) * (1 - tx)
    wb = (1 - ty) * tx
    wc = ty * (1 - tx)
    wd = ty * tx
    p = wa * a + wb * b + wc * c + wd * d
    vp = wa * var[y0, x0] + wb * var[y0, x1] + wc * var[y1, x0] + wd * var[y1, x1]
    lo = min(min(a, b), min(c, d))
    hi = max(max(a, b), max(c, d))
    s = np.float32(4.0) * max(ty * (1 - ty), tx * (1 - tx))
    half = np.float32(0.5) * (hi - lo)
    return p, vp + half * half * s + extra


@njit(cache=True, nogil=True, parallel=True)
def _judge_blocks(values, state, prev, var, cy, cx, bs, dec, cand, g, floor, nd, z_mean, out_share, tol,
                  z_out, min_ev, rec_noise, rec_tol, reuse_frames, mis):
    """Per block: the candidate motion (`_candidates`: (cy[c], cx[c])) that explains the measured pixels
    (VALID and NOISY) best, and the decision (FRESH, REFRESH, REUSE, NO_PRIOR, NO_EVIDENCE)."""
    h, w = values.shape
    nby, nbx = dec.shape
    nc = cy.shape[0]
    for by in prange(nby):
        for bx in range(nbx):
            y0 = by * bs
            x0 = bx * bs
            y1 = min(y0 + bs, h)
            x1 = min(x0 + bs, w)
            best_m = np.float32(np.inf)
            best_o = 0
            best_n = 0
            best_c = 0
            for c in range(nc):
                sy = cy[c]
                sx = cx[c]
                zs = np.float32(0.0)
                n = 0
                no = 0
                for y in range(y0, y1):
                    for x in range(x0, x1):
                        st = state[y, x]
                        r = st & REASON_MASK
                        if r != VALID and r != NOISY:
                            continue
                        p, vp = _aligned(prev, var, y, x, sy, sx, h, w, mis if c > 0 else np.float32(0.0))
                        if not vp < np.inf:
                            continue
                        vm = _meas_var(p, (st & ATTENUATED) != 0 or r == NOISY, g, floor, nd)
                        d = values[y, x] - p
                        t = tol * p
                        z = d * d / (vm + vp + t * t)
                        zs += min(z, z_out)
                        n += 1
                        no += 1 if z > z_out else 0
                m = zs / n if n > 0 else np.float32(np.inf)
                if c == 0 or m < best_m * np.float32(0.8):     # a later candidate must explain clearly better
                    best_m = m
                    best_o = no
                    best_n = n
                    best_c = c
                if m < np.float32(0.6) * z_mean and no == 0:
                    break          # explained well: the later candidates are not tried
            cand[by, bx] = best_c
            if best_n < min_ev:
                dec[by, bx] = NO_EVIDENCE
            elif best_m >= z_mean or best_o > max(np.float32(1.0), out_share * best_n):
                dec[by, bx] = FRESH
            elif best_o > 0:
                dec[by, bx] = NO_PRIOR
            else:
                # reusable when the past of every missing pixel averages `reuse_frames` reconstructions (or
                # noisy measurements)
                sy = cy[best_c]
                sx = cx[best_c]
                settled = True
                for y in range(y0, y1):
                    for x in range(x0, x1):
                        r = state[y, x] & REASON_MASK
                        if r == VALID:
                            continue
                        p, vp = _aligned(prev, var, y, x, sy, sx, h, w, mis if best_c > 0 else np.float32(0.0))
                        ref = _rec_var(p, g, floor, rec_noise, rec_tol)
                        if r == NOISY:     # a noisy measurement: settled as well once its average is
                            vm = _meas_var(p, True, g, floor, nd)
                            ref = vm if vm > ref else ref
                        if not vp * reuse_frames <= np.float32(1.01) * ref:
                            settled = False
                            break
                    if not settled:
                        break
                dec[by, bx] = REUSE if settled else REFRESH


@njit(cache=True, nogil=True, parallel=True)
def _prepare_work(values, state, prev, var, cy, cx, bs, dec, cand, known, lower, upper, use_bounds, work, pv,
                  pvar, g, floor, nd, tol, z_out, max_frames, mis):
    """The reconstruction's input: `work` = the values with measured pixels of trusted blocks averaged with
    their aligned past (inverse variance; an outlier restarts its pixel), missing pixels of REUSE blocks =
    their past within their bounds and known (NOISY ones averaged with their measurement); pv / pvar =
    the aligned past where a missing pixel is to be fused with it (pvar inf: no past) or, at measured and
    reused pixels, the new value's variance."""
    h, w = values.shape
    inf = np.float32(np.inf)
    for y in prange(h):
        by = y // bs
        for x in range(w):
            d = dec[by, x // bs]
            st = state[y, x]
            r = st & REASON_MASK
            v = values[y, x]
            att = (st & ATTENUATED) != 0
            work[y, x] = v
            pv[y, x] = v
            if r == VALID:
                pvar[y, x] = _meas_var(v, att, g, floor, nd)
            else:
                pvar[y, x] = inf
            if d == FRESH or d == NO_EVIDENCE:
                continue
            c = cand[by, x // bs]
            p, vp = _aligned(prev, var, y, x, cy[c], cx[c], h, w, mis if c > 0 else np.float32(0.0))
            if not vp < inf:
                continue
            if r == VALID or (d == REUSE and r == NOISY):
                vm = _meas_var(p, att or r == NOISY, g, floor, nd)
                dd = v - p
                t = tol * p
                if dd * dd > z_out * (vm + vp + t * t):
                    pvar[y, x] = vm               # an outlier: the pixel restarts
                    if r == NOISY:
                        pvar[y, x] = inf          # reconstructed alone
                    continue
                vpp = vp if vp > vm / max_frames else vm / max_frames
                a = (v * vpp + p * vm) / (vm + vpp)
                nv = vm * vpp / (vm + vpp)
                work[y, x] = a
                pv[y, x] = a
                nv = nv if nv > vm / max_frames else vm / max_frames
                pvar[y, x] = nv if r == VALID else -nv    # negative: a reused pixel, as it is
                known[y, x] = True
            elif d == REUSE:
                if use_bounds:
                    lb = lower[y, x]
                    ub = upper[y, x]
                    p = lb if (r == CLIPPED) & (lb == lb) & (lb > p) else p
                    p = ub if (r == DARK) & (ub == ub) & (ub < p) else p
                work[y, x] = p
                pv[y, x] = p
                pvar[y, x] = -vp                  # negative: reused as it is
                known[y, x] = True
            elif d == REFRESH:
                pv[y, x] = p
                pvar[y, x] = vp


@njit(cache=True, nogil=True, parallel=True)
def _finish(values, state, work, pv, pvar, prev, var, lower, upper, use_bounds, g, rec_noise, rec_tol,
            reuse_frames, floor):
    """Write the frame and keep it as the past: measured pixels get their average, missing pixels the
    reconstruction fused by inverse variance with their aligned past (where they have one), within their
    bounds, with RECONSTRUCTED. Returns the number of missing pixels written."""
    h, w = values.shape
    flag = np.uint8(RECONSTRUCTED)
    n = 0
    for y in prange(h):
        c = 0
        for x in range(w):
            st = state[y, x]
            r = st & REASON_MASK
            a = work[y, x]
            if r == VALID:
                values[y, x] = a
                prev[y, x] = a
                var[y, x] = pvar[y, x]
                continue
            vp = pvar[y, x]
            p = pv[y, x]
            vr = _rec_var(a, g, floor, rec_noise, rec_tol)
            nv = vr
            if vp < np.float32(0.0):
                nv = -vp                                      # reused: the past as it is
            elif vp < np.float32(np.inf):
                a = (a * vp + p * vr) / (vr + vp)
                if use_bounds:
                    lb = lower[y, x]
                    ub = upper[y, x]
                    a = lb if (r == CLIPPED) & (lb == lb) & (lb > a) else a
                    a = ub if (r == DARK) & (ub == ub) & (ub < a) else a
                nv = vr * vp / (vr + vp)
                lim = _rec_var(a, g, floor, rec_noise, rec_tol) / reuse_frames   # at the value kept
                nv = nv if nv > lim else lim
            values[y, x] = a
            state[y, x] = st | flag
            prev[y, x] = a
            var[y, x] = nv
            c += 1
        n += c
    return n
