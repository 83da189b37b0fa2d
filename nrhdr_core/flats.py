"""Flat-field analysis without a mask: the ND pixel positions, the ND factor and the defect pixels of a sensor
from its flat-field sweep alone (docs/CROSSTALK.md section 3, "Without a mask").

`detect` runs these steps on a `calibration.FlatSweep`:
1. levels (`calibration.sensor_levels`, all pixels as one population) and constant pixels (the same code
   in every frame of the sweep);
2. each pixel's response: slope of a weighted line fit of its mean code against exposure (weights from the
   sweep's photon transfer, one pass rejecting points beyond `REJECT_Z` of the noise) over the exposures
   where 99 % of the pixels are below `LINEAR_LIMIT` of the range (neighbours far from saturation: no
   blooming) and the pixel itself is unclipped;
3. log response relative to the local log response of the regular pixels (a plane fitted to them in a box
   of `window` pixels, their crosstalk removed once it is known): vignetting, illumination gradients and
   PRNU cancel; regular pixels sit near 0, attenuated ones near -log(ND);
4. classification, iterated: a first split by Otsu's threshold on the log response relative to the local
   mean of all pixels; then crosstalk is modelled as a linear share of the response per neighbour of the
   other kind (edge and corner neighbours apart, fitted per population like `calibration.reference_curves`),
   removed under each hypothesis, and a pixel joins the population whose centre its corrected log response
   is nearer to (the threshold is half-way between the centres: sqrt(ND) x the attenuated response);
5. ND = ratio of the populations' crosstalk-free responses (the regressions' intercepts; on the checkerboard,
   where every interior pixel of a kind has the same neighbours, they rest on the sensor's border pixels);
6. defects: hot (dark code more than max(`HOT_SIGMA` robust sigmas, `HOT_SHARE` of the range) above black,
   or a response above `HOT_RESPONSE` x the regular pixels': dark current), dead (response below
   `DEAD_RESPONSE` x the attenuated pixels', none, or one code at or below black throughout), stuck (one
   code above black throughout, step 1); dead and stuck pixels take the kind opposite to most of their four
   edge neighbours;
7. confidence: the populations' separation (distance of their centres in corrected log response over the
   pooled robust sigma) and the share of ambiguous pixels (farther than a third of that distance from both
   centres); `confident` needs separation >= `MIN_SEPARATION` and ambiguous <= `MAX_AMBIGUOUS`.
A Bayer sensor (`cfa`): steps 3-5 within each CFA class (its photosites share one colour and the colours
around them; the channels respond differently), the ND the median of the classes'.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from . import calibration, crosstalk
from . import profile as profiles
from .calibration import CalibrationError

DEFECT_GOOD = 0  # defect-map codes: the profile's (profile.DEFECT_HOT / DEAD / STUCK)
DEFECT_HOT, DEFECT_DEAD, DEFECT_STUCK = profiles.DEFECT_HOT, profiles.DEFECT_DEAD, profiles.DEFECT_STUCK

LINEAR_LIMIT = 0.7        # fit only exposures where 99 % of the pixels are below this share of the range
REJECT_Z = 6.0            # a fit point this many noise sigmas off the line is rejected (one pass)
WINDOW = 9                # box (pixels) of the local regular response
HOT_SIGMA = 8.0           # hot: dark code above black by this many robust sigmas of the dark codes ...
HOT_SHARE = 0.01          # ... and by at least this share of the range (clip code - black)
HOT_RESPONSE = 1.5        # hot: response above this x the regular pixels' (dark current)
DEAD_RESPONSE = 0.25      # dead: response below this x the attenuated pixels'
STUCK_VAR = 0.25          # stuck: temporal variance at most this (DN^2) at every exposure ...
STUCK_RANGE = 1.0         # ... and mean code within this (DN) over the whole sweep
MIN_SEPARATION = 8.0      # confident: separation at least this ...
MAX_AMBIGUOUS = 0.001     # ... and at most this share of ambiguous pixels
_EDGE = np.array([dy == 0 or dx == 0 for dy, dx in crosstalk.DIRS])


@dataclasses.dataclass
class MaskDetection:
    """What `detect` found in a flat-field sweep."""
    mask: np.ndarray              # (H, W) bool, True = attenuated
    nd: float                     # ratio of the populations' crosstalk-free responses
    defects: np.ndarray           # (H, W) uint8: DEFECT_GOOD / HOT / DEAD / STUCK
    log_response: np.ndarray      # (H, W) float32 corrected log response of the pixel's own kind, relative to
                                  # the local regular response (NaN for dead and stuck pixels)
    centres: tuple                # (attenuated, regular) population centres in log_response
    sigmas: tuple                 # (attenuated, regular) robust sigmas
    separation: float             # centre distance / pooled robust sigma
    ambiguous: float              # share of classified pixels farther than a third of the distance from both
    ambiguous_pixels: int         # their number
    nd_border_only: bool          # a neighbour count hardly varies inside a population (the checkerboard): the
                                  # ND's crosstalk correction rests on the sensor's border pixels
    crosstalk_share: dict         # response added per neighbour of the other kind, share of the own response
    exposures_used: int

    @property
    def confident(self) -> bool:
        return self.separation >= MIN_SEPARATION and self.ambiguous <= MAX_AMBIGUOUS

    def counts(self) -> dict:
        return {"hot": int(np.sum(self.defects == DEFECT_HOT)), "dead": int(np.sum(self.defects == DEFECT_DEAD)),
                "stuck": int(np.sum(self.defects == DEFECT_STUCK))}

    def summary(self) -> dict:
        """The figures `nrhdr calibrate` reports and saves with the profile."""
        return {"attenuated_share": round(float(self.mask.mean()), 5), "nd": round(self.nd, 4),
                "nd_border_only": self.nd_border_only,
                "separation": round(self.separation, 2), "ambiguous_share": round(self.ambiguous, 6),
                "ambiguous_pixels": self.ambiguous_pixels,
                "confident": bool(self.confident),
                "min_separation": MIN_SEPARATION, "max_ambiguous_share": MAX_AMBIGUOUS,
                "centres_log": [round(c, 4) for c in self.centres],
                "sigmas_log": [round(s, 5) for s in self.sigmas],
                "crosstalk_share": {k: round(v, 5) for k, v in self.crosstalk_share.items()},
                "defects": self.counts(), "defect_pixels": self.defect_list(),
                "exposures_used": self.exposures_used}

    def write_plot(self, path):
        """Histogram of the corrected log responses by found kind (the check of a detection); returns path."""
        return _write_plot(self, path)

    def defect_list(self, limit: int = 1000) -> list:
        """[[y, x, "hot" | "dead" | "stuck"], ...] of the first `limit` defect pixels (row-major)."""
        names = {DEFECT_HOT: "hot", DEFECT_DEAD: "dead", DEFECT_STUCK: "stuck"}
        ys, xs = np.nonzero(self.defects)
        return [[int(y), int(x), names[int(self.defects[y, x])]] for y, x in zip(ys[:limit], xs[:limit])]


def finder(clip_code: int | None = None, bit_depth: int | None = None, accept_low_confidence: bool = False,
           cfa: str = "none"):
    """`find_mask` for calibration.run_calibrate: `detect`, then `check_confidence`."""
    def find(sweep: calibration.FlatSweep) -> MaskDetection:
        det = detect(sweep, clip_code=clip_code, bit_depth=bit_depth, cfa=cfa)
        check_confidence(det, str(sweep.folder), accept_low_confidence)
        return det
    return find


def check_confidence(det: MaskDetection, where: str, accept: bool = False) -> None:
    """CalibrationError unless the detection is confident (or `accept`): the message gives the figures and
    what to do."""
    if det.confident or accept:
        return
    raise CalibrationError(
        f"{where}: the ND pixels cannot be told apart reliably from these flats: the two populations are "
        f"{det.separation:.1f} sigma apart (need >= {MIN_SEPARATION:g}) and {det.ambiguous * 100:.3f} % of the "
        f"pixels are ambiguous (at most {MAX_AMBIGUOUS * 100:g} %); capture more frames per exposure or "
        f"brighter exposures below saturation, pass the mask with --mask, or accept the result with "
        f"--accept-low-confidence")


def detect(sweep: calibration.FlatSweep, clip_code: int | None = None, bit_depth: int | None = None,
           window: int = WINDOW, iterations: int = 4, cfa: str = "none") -> MaskDetection:
    """The ND mask, ND factor and defect map of the sensor that captured `sweep` (module doc). `cfa`: a
    Bayer sensor's phase: the channels respond differently, so every comparison stays within one CFA class
    (the photosites of one place in the 2 x 2 block: one colour, the same colours around them; the box of
    the local response is 2 x `window` - 1 so that it holds as many of them), and the ND is the median of
    the classes' (module doc, steps 3-5)."""
    from . import cfa as cfas
    where = str(sweep.folder)
    H, W = sweep.shape
    classes = None
    if cfas.is_colour(cfa):
        if H % 2 or W % 2:
            raise CalibrationError(f"{where}: a Bayer sensor's frames have an even width and height, got {W}x{H}")
        cls = calibration._cfa_class(H, W)
        classes = [cls == q for q in range(4)]
        window = 2 * window - 1
    try:
        lv = calibration.sensor_levels(sweep, np.zeros((H, W), bool), clip_code, bit_depth)
    except CalibrationError as e:
        raise CalibrationError(f"{e} (without a mask all pixels count as one population here: every pixel, "
                               f"attenuated ones included, must saturate at the longest exposure)") from None
    constant = (sweep.tvar.max(0) <= STUCK_VAR) & (np.ptp(sweep.mean, axis=0) <= STUCK_RANGE)
    stuck = constant & (sweep.mean[0] > lv.black + STUCK_RANGE)       # a constant code at black: dead
    if constant.all():
        raise CalibrationError(f"{where}: every pixel reads one code throughout the sweep")
    slope, offset, used = pixel_response(sweep, lv, constant)
    dark_frame = sweep.exposures[0] == 0
    dark = lv.dark if dark_frame else offset
    hot = _hot_offset(dark, lv, constant)
    with np.errstate(divide="ignore", invalid="ignore"):
        L = np.where(slope > 0, np.log(slope), np.nan)
    ok = ~constant & np.isfinite(L)
    if ok.sum() < 16:
        raise CalibrationError(f"{where}: fewer than 16 pixels respond to the exposure")
    # first split: log response relative to the local mean of all pixels, Otsu's threshold
    if classes is None:
        r0 = L - _local_mean(L, ok & ~hot, window)
    else:
        r0 = np.zeros((H, W))
        for c in classes:
            r0[c] = (L - _local_mean(L, ok & ~hot & c, window))[c]
    att = r0 < _otsu(r0[ok])
    pop = ok.copy()
    st = None
    for _ in range(iterations):         # classification and the crosstalk-free local response, in turn
        st = _class_populations(L, att, pop, window, st, classes)
        att = ok & (np.abs(st.la - st.mu_att) < np.abs(st.lr - st.mu_reg))
        # dead: far below the attenuated pixels; hot: far above the regular ones
        dead = ~np.isfinite(L) | (st.y < DEAD_RESPONSE * st.b0)
        hot_resp = st.y > HOT_RESPONSE * st.a0
        pop = ok & ~dead & ~hot_resp & ~hot
    st = _class_populations(L, att, pop, window, st, classes)
    defects = np.zeros((H, W), np.uint8)
    defects[hot | (hot_resp & ok)] = DEFECT_HOT
    defects[~stuck & (dead | constant)] = DEFECT_DEAD
    defects[stuck] = DEFECT_STUCK
    unknown = (defects == DEFECT_DEAD) | (defects == DEFECT_STUCK)
    att = att & ~unknown
    att |= unknown & _opposite_of_neighbours(att, unknown)
    own = np.where(att, st.la, st.lr).astype(np.float32)
    own[unknown] = np.nan
    sel = pop & ~unknown
    gap = st.mu_reg - st.mu_att
    with np.errstate(invalid="ignore"):
        amb = sel & (np.abs(st.la - st.mu_att) > gap / 3) & (np.abs(st.lr - st.mu_reg) > gap / 3)
    pooled = math.sqrt(0.5 * (st.s_att ** 2 + st.s_reg ** 2))
    separation = gap / pooled if pooled > 0 else float("inf")
    n_amb = int(amb.sum())
    if not (att.any() and (~att).any()) or gap <= 0:
        separation, amb_share, n_amb = 0.0, 1.0, int(sel.sum())
    else:
        amb_share = n_amb / max(int(sel.sum()), 1)
    nd = st.nd
    return MaskDetection(att, float(nd), defects, own, (st.mu_att, st.mu_reg), (st.s_att, st.s_reg),
                         float(separation), amb_share, n_amb, not st.corrected, st.share, int(used))


# ---- the response of each pixel --------------------------------------------------------------------------

def pixel_response(sweep: calibration.FlatSweep, lv: calibration.SensorLevels, skip=None, rows: int = 128):
    """(slope (H, W) DN/s, offset (H, W) DN, exposures used): weighted line fit of each pixel's mean code
    against exposure over the dark frame and the lit exposures where 99 % of the pixels are below
    LINEAR_LIMIT of the range, only where the pixel is unclipped (and, by a first unweighted fit, more than
    3 read-noise sigmas above code 0: a sensor without black offset cuts the noise there); weights
    1 / variance of the mean from the photon transfer (var = k signal + v0, fitted over all pixels) at the
    signal of the first fit (weights from the noisy points themselves would bias the slope low); one pass
    drops points beyond REJECT_Z sigmas. NaN where fewer than two points remain."""
    where = str(sweep.folder)
    t = sweep.exposures.astype(np.float64)
    E = t.size
    H, W = sweep.shape
    skip = np.zeros((H, W), bool) if skip is None else skip
    step = max(1, int(math.sqrt(H * W / 65536)))          # percentiles from a subsample of large sensors
    sub = ~skip[::step, ::step]
    hi = np.array([np.percentile(lv.signal[i][::step, ::step][sub], 99) if lv.lit[i] else 0.0 for i in range(E)])
    use = lv.lit & (hi < LINEAR_LIMIT * lv.top)
    idx = np.nonzero(use | ~lv.lit)[0]
    if use.sum() < 1 or idx.size < 2:
        raise CalibrationError(f"{where}: no exposure with light where the pixels are in their linear range "
                               f"(99 % below {LINEAR_LIMIT * 100:.0f} % of saturation); without a mask the sweep "
                               f"needs such exposures (and a dark frame, or two of them)")
    k, v0 = _noise_model(sweep, lv, use, step, sub)
    floor = 3.0 * math.sqrt(v0)              # the noise of a mean this close to code 0 is cut by the ADC
    slope = np.full((H, W), np.nan)
    offset = np.full((H, W), np.nan)
    x = t[idx][:, None, None]
    n = sweep.frames[idx].astype(np.float64)[:, None, None]
    for y0 in range(0, H, rows):
        ys = slice(y0, min(H, y0 + rows))
        Y = sweep.mean[idx, ys].astype(np.float64)
        unc = lv.unclipped[idx, ys]
        a, b = _line_fit(x, Y, unc.astype(np.float64))           # unweighted: the signal for the weights
        unc &= a + b * x > floor                                 # not clipped, at either end
        w = np.where(unc, n / (k * np.maximum(np.nan_to_num(b) * x, 0.0) + v0), 0.0)
        a, b = _line_fit(x, Y, w)
        z = (Y - a - b * x) * np.sqrt(w)
        keep = (np.abs(z) <= REJECT_Z) | (w == 0)
        enough = (keep & (w > 0)).sum(0) >= 2
        w2 = np.where(keep | ~enough[None], w, 0.0)
        a, b = _line_fit(x, Y, w2)
        slope[ys], offset[ys] = b, a
    return slope, offset, int(use.sum())


def _noise_model(sweep, lv, use, step, sub):
    """(k, v0): temporal variance of a frame = k x signal + v0 over the pixels (photon transfer)."""
    sel = [(i, sub & lv.unclipped[i][::step, ::step]) for i in np.nonzero(use)[0]]
    s = np.concatenate([lv.signal[i][::step, ::step][m] for i, m in sel])
    v = np.concatenate([sweep.tvar[i][::step, ::step][m] for i, m in sel])
    if not lv.lit[0]:
        v0 = float(np.mean(sweep.tvar[0][::step, ::step][sub]))
    else:
        v0 = float("nan")
    keep = v <= np.percentile(v, 99.5) if v.size else v.astype(bool)
    k = float("nan")
    if keep.sum() >= 3 and np.ptp(s[keep]) > 0:
        k, c = np.polyfit(s[keep], v[keep], 1)
        if not math.isfinite(v0):
            v0 = float(c)
    if not (math.isfinite(k) and k > 0):
        k = 0.0
    v0 = max(v0 if math.isfinite(v0) else 1.0, 1.0 / 12.0)
    return k, v0


def _line_fit(x, Y, w):
    """(a, b) of the weighted least-squares line Y = a + b x along axis 0 (NaN with fewer than 2 points)."""
    sw = w.sum(0)
    sx = (w * x).sum(0)
    sy = (w * Y).sum(0)
    sxx = (w * x * x).sum(0)
    sxy = (w * x * Y).sum(0)
    det = sw * sxx - sx * sx
    with np.errstate(divide="ignore", invalid="ignore"):
        b = np.where(det > 1e-12 * np.maximum(sw * sxx, 1e-300), (sw * sxy - sx * sy) / det, np.nan)
        a = (sy - b * sx) / sw
    return a, b


def _hot_offset(dark, lv, stuck):
    """Pixels whose dark code is more than max(HOT_SIGMA robust sigmas, HOT_SHARE of the range) above black."""
    d = dark[~stuck & np.isfinite(dark)]
    med = float(np.median(d))
    sig = 1.4826 * float(np.median(np.abs(d - med)))
    lim = med + max(HOT_SIGMA * sig, HOT_SHARE * lv.top)
    with np.errstate(invalid="ignore"):
        return ~stuck & (dark > lim)


# ---- the two populations ---------------------------------------------------------------------------------

@dataclasses.dataclass
class _Populations:
    field: np.ndarray              # (H, W) local log response of the regular pixels
    y: np.ndarray                  # (H, W) response relative to the local regular response
    la: np.ndarray                 # (H, W) log response if the pixel were attenuated (its crosstalk removed)
    lr: np.ndarray                 # (H, W) ... if it were regular
    mu_att: float
    mu_reg: float
    s_att: float
    s_reg: float
    a0: float                      # crosstalk-free regular response (relative to the local regular response;
    b0: float                      # crosstalk-free attenuated response          colour: per-pixel maps of the class's)
    corrected: bool
    share: dict
    classes_nd: float | None = None  # a colour sensor: the median of its CFA classes' ND

    @property
    def nd(self) -> float:
        """The ND factor: ratio of the crosstalk-free responses (a colour sensor: `classes_nd`)."""
        if self.classes_nd is not None:
            return self.classes_nd
        return float(self.a0 / self.b0) if self.b0 > 0 else float("nan")


def _class_populations(L, att, pop, window, prev, classes) -> _Populations:
    """`_populations` of a monochrome sensor (`classes` None), or of each CFA class apart (a list of 4 bool
    maps) merged: per-pixel fields from the pixel's class, a0 and b0 as per-pixel maps of the class's values,
    the centres over all classes (responses relative to the class's own regular response), the ND the
    median of the classes'."""
    if classes is None:
        return _populations(L, att, pop, window, prev)
    parts = [_populations(L, att, pop & c, window, prev) for c in classes]
    field, y, la, lr = (np.zeros(L.shape) for _ in range(4))
    a0, b0 = np.zeros(L.shape), np.zeros(L.shape)
    for c, p in zip(classes, parts):
        for arr, v in ((field, p.field), (y, p.y), (la, p.la), (lr, p.lr), (a0, p.a0), (b0, p.b0)):
            arr[c] = v[c] if np.ndim(v) else v
    mu_att, s_att = _centre(la[pop & att])
    mu_reg, s_reg = _centre(lr[pop & ~att])
    nds = [p.a0 / p.b0 for p in parts if p.b0 > 0]
    share = {k: float(np.mean([p.share[k] for p in parts])) for k in parts[0].share}
    return _Populations(field, y, la, lr, mu_att, mu_reg, s_att, s_reg, a0, b0, all(p.corrected for p in parts),
                        share, float(np.median(nds)) if nds else float("nan"))


def _populations(L, att, pop, window, prev=None) -> _Populations:
    """Both hypotheses' corrected log responses and the populations' robust centres, given a classification
    (`att`) of the pixels `pop` that represent their population. The local regular response comes from the
    regular pixels' responses with their crosstalk removed by `prev` (the previous iteration, where its
    regressions were identifiable), so that it does not depend on how many attenuated pixels are around."""
    reg = pop & ~att
    a_sel = pop & att
    field = _local_mean(L if prev is None or not prev.corrected else prev.lr + prev.field, reg, window)
    y = np.exp(L - field)
    ne_reg, nc_reg = _neighbour_counts(att, True)
    ne_att, nc_att = _neighbour_counts(att, False)
    b0, bcoef, bcorr = _share_fit(y[a_sel], ne_reg[a_sel], nc_reg[a_sel])
    a0, acoef, acorr = _share_fit(y[reg], ne_att[reg], nc_att[reg])
    with np.errstate(divide="ignore", invalid="ignore"):
        la = np.log(np.maximum(y - bcoef[0] * ne_reg - bcoef[1] * nc_reg, 1e-6 * max(b0, 1e-12)))
        lr = np.log(np.maximum(y - acoef[0] * ne_att - acoef[1] * nc_att, 1e-6))
    mu_att, s_att = _centre(la[a_sel])
    mu_reg, s_reg = _centre(lr[reg])
    share = {"attenuated_per_regular_edge": bcoef[0] / b0 if b0 > 0 else float("nan"),
             "attenuated_per_regular_corner": bcoef[1] / b0 if b0 > 0 else float("nan"),
             "regular_per_attenuated_edge": acoef[0] / a0 if a0 > 0 else float("nan"),
             "regular_per_attenuated_corner": acoef[1] / a0 if a0 > 0 else float("nan")}
    return _Populations(field, y, la, lr, mu_att, mu_reg, s_att, s_reg, a0, b0, bcorr and acorr, share)


def _share_fit(y, ne, nc):
    """(intercept, (per edge, per corner), identifiable) of y ~ 1 + ne + nc (robust least squares, as
    calibration.reference_curves, with the neighbours counted by kind: edge and corner); a count that takes
    one value in all but max(20, 2 %) of the population gets no coefficient (identifiable False)."""
    if y.size < 3:
        return (float(np.median(y)) if y.size else float("nan")), (0.0, 0.0), False
    cols = [np.ones(y.size)]
    which = []
    for j, c in enumerate((ne, nc)):
        if np.bincount(c.astype(np.int64)).max() <= c.size - max(20, 0.02 * c.size):
            cols.append(c.astype(np.float64))
            which.append(j)
    coef = calibration._robust_lstsq(np.column_stack(cols), y.astype(np.float64))
    out = [0.0, 0.0]
    for j, c in zip(which, coef[1:]):
        out[j] = float(c)
    return float(coef[0]), tuple(out), len(which) == 2


def _neighbour_counts(att, want_regular):
    """(edge, corner) counts of each pixel's neighbours that are regular (want_regular) or attenuated."""
    ind = calibration._neighbour_indicators(att, want_regular)
    return ind[_EDGE].sum(0), ind[~_EDGE].sum(0)


def _centre(v):
    """(median, robust sigma 1.4826 MAD) of the finite values."""
    v = v[np.isfinite(v)]
    if v.size == 0:
        return float("nan"), float("nan")
    m = float(np.median(v))
    return m, max(1.4826 * float(np.median(np.abs(v - m))), 1e-6)


def _local_mean(v, sel, window):
    """Local value of `v` from the pixels `sel` in a window x window box around each pixel: a plane fitted by
    least squares (box-filtered moments; unbiased by a gradient, also at the sensor's border, where the box
    is cut), its mean where the box's pixels do not determine a plane; the box grows where it holds none."""
    from scipy.ndimage import uniform_filter
    w = (sel & np.isfinite(v)).astype(np.float64)
    vv = np.where(w > 0, v, 0.0).astype(np.float64)
    H, W = v.shape
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    out = np.full(v.shape, np.nan)
    size = int(window)
    while True:
        def box(a):
            return uniform_filter(a, size, mode="constant", cval=0.0)
        s1, sx, sy = box(w), box(w * xx), box(w * yy)
        with np.errstate(divide="ignore", invalid="ignore"):
            mx, my = sx / s1, sy / s1                            # centroid of the selected pixels
            cxx = box(w * xx * xx) / s1 - mx * mx
            cyy = box(w * yy * yy) / s1 - my * my
            cxy = box(w * xx * yy) / s1 - mx * my
            mv = box(w * vv) / s1
            cxv = box(w * xx * vv) / s1 - mx * mv
            cyv = box(w * yy * vv) / s1 - my * mv
            det = cxx * cyy - cxy * cxy
            plane = (det > 0.2 * size ** 4 / 144) & (s1 * size * size >= 12)   # at least ~2/3 of the box
            gx = np.where(plane, (cxv * cyy - cyv * cxy) / det, 0.0)
            gy = np.where(plane, (cyv * cxx - cxv * cxy) / det, 0.0)
            val = mv + gx * (xx - mx) + gy * (yy - my)
        good = np.isnan(out) & (s1 > 0.5 / (size * size)) & np.isfinite(val)
        out[good] = val[good]
        if not np.isnan(out).any() or size >= 2 * max(v.shape):
            break
        size *= 2
    if np.isnan(out).any():
        out[np.isnan(out)] = float(np.mean(v[w > 0])) if w.any() else 0.0
    return out


def _otsu(v, bins: int = 256) -> float:
    """Otsu's threshold of the values (between their 0.1 and 99.9 percentiles)."""
    lo, hi = np.percentile(v, [0.1, 99.9])
    if not hi > lo:
        return float(hi)
    h, edges = np.histogram(np.clip(v, lo, hi), bins=bins, range=(lo, hi))
    c = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(h)
    w1 = w0[-1] - w0
    m0 = np.cumsum(h * c)
    with np.errstate(divide="ignore", invalid="ignore"):
        between = w0 * w1 * (m0 / w0 - (m0[-1] - m0) / w1) ** 2
    between[~np.isfinite(between)] = -1
    j = int(np.argmax(between))
    return float(edges[j + 1])


def _opposite_of_neighbours(att, unknown):
    """For pixels of unknown kind: True (attenuated) where most of their known edge neighbours are regular."""
    known = ~unknown
    n_att = np.zeros(att.shape)
    n_known = np.zeros(att.shape)
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        n_att += crosstalk._shift((att & known).astype(np.float64), dy, dx)
        n_known += crosstalk._shift(known.astype(np.float64), dy, dx)
    return 2 * n_att < n_known


def _write_plot(det: MaskDetection, path):
    """Histogram of the corrected log responses by found kind, the centres and the threshold (the check of
    a detection: two narrow peaks about log(ND) apart, nothing in between)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    v = det.log_response
    ok = np.isfinite(v)
    lo, hi = np.percentile(v[ok], [0.01, 99.99]) if ok.any() else (-3.0, 1.0)
    bins = np.linspace(min(lo, det.centres[0]) - 0.1, max(hi, det.centres[1]) + 0.1, 200)
    fig, ax = plt.subplots(figsize=(6, 4), dpi=90)
    ax.hist(v[ok & det.mask], bins=bins, color="tab:blue", label="attenuated")
    ax.hist(v[ok & ~det.mask], bins=bins, color="tab:orange", label="regular")
    ax.set_yscale("log")
    for c in det.centres:
        ax.axvline(c, color="k", ls=":", lw=1)
    ax.axvline(0.5 * sum(det.centres), color="r", ls="--", lw=1, label="threshold")
    ax.set_xlabel("log response relative to the local regular response (crosstalk removed)")
    ax.set_ylabel("pixels")
    ax.set_title(f"Mask from the flats: ND {det.nd:.3f}, separation {det.separation:.1f}, "
                 f"ambiguous {det.ambiguous * 100:.3f} %", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
