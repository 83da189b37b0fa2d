"""FSE block kernel: the Frequency Selective Extrapolation of one quadtree leaf (Seiler & Kaup, SPL 2010;
fse-reference.md "The model, one block at a time"), one step per function:

1. :func:`gather`: weights w = s rho^r and values f of the N x N support area;
2. :func:`moments`, :func:`iteration_count`: weighted mean (removed) and the texture-adaptive iteration
   count (Genser et al., IWSSIP 2017);
3. :func:`forward_dft`: W = DFT(w) and R = DFT(w (f - mean)) as one complex FFT (:func:`fft_pass`);
4. :func:`extrapolate`: the iterations: basis selection (:func:`select_bin`, spectral prior of Genser et
   al., IWSSIP 2018), coefficient c = gamma R(k) / W(0) and the residual update in the frequency domain
   (:func:`update_pair`, :func:`update_self`);
5. :func:`synthesize`: the model on the block from its coefficients;
6. :func:`write_block`: the block's missing pixels, clamped to their bounds.

The records the kernels take: :data:`Frame` (working image, state, bounds), :data:`Params` (scalars),
:data:`Context` (frame, ``plan.Plan``, ``params.Tables``, params: what every block reads) and
:data:`Scratch` (one thread's work arrays). ``noisy`` is the pair (wp, mest) of the joint estimation.

The helpers take the window size ``n`` as an argument and are inlined (numba IR, ``inline="always"``) into
the block kernel that :func:`make_block_kernel` builds: in the kernel for a fixed window ``n`` is a
compile-time constant of the factory's closure, so the short loops get fixed trip counts that LLVM unrolls
and vectorises; the generic kernel reads ``n`` from the tables at run time. One source, several
specialisations, all cached by numba (its cache keys a closure by the values it closes over).
"""
from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from .params import KNOWN, MISSING, NOISY, RECONSTRUCTED

__all__ = ["Frame", "Params", "Context", "Scratch", "make_scratch", "make_block_kernel", "block16",
           "block32", "block_generic", "block16_joint", "block_joint"]

# img: working image (float32, working domain); state: working states (params.MISSING...); lo/hi: bounds
# of the missing pixels in the working domain ((1, 1) dummies when unused)
Frame = namedtuple("Frame", "img state lo hi")
# delta: weight of reconstructed pixels; gamma: orthogonality-deficiency compensation; iter_c, iter_min,
# iter_max: iteration count rule; scale: data scale of sigma; use_lo/use_hi: clamp to lo/hi
Params = namedtuple("Params", "delta gamma iter_c iter_min iter_max scale use_lo use_hi")
Context = namedtuple("Context", "frame plan tab par")
# wbuf/xbuf: weights / values of the support area (n, n), then the block's model; zb: the FFT's work area
# (4 n^2); wr/wi: W on the doubled periodic grid (2n, 2n); rr/ri: R on the half spectrum (n/2 + 1, n);
# en: selection energies |R|^2 prior^2; rm: their row maxima; sel_u/sel_v/sel_r/sel_i: the model's
# coefficients (bin, 2 Re c, 2 Im c)
Scratch = namedtuple("Scratch", "wbuf xbuf zb wr wi rr ri en rm sel_u sel_v sel_r sel_i")

_INL = dict(cache=True, nogil=True, fastmath=True, inline="always")


@njit(cache=True, nogil=True)
def make_scratch(n, nsel):
    """One thread's :data:`Scratch` for an n x n window and up to ``nsel`` coefficients (a few kB)."""
    hh = n // 2 + 1
    return Scratch(np.zeros((n, n), np.float32), np.zeros((n, n), np.float32),
                   np.zeros(4 * n * n, np.float32),
                   np.zeros((2 * n, 2 * n), np.float32), np.zeros((2 * n, 2 * n), np.float32),
                   np.zeros((hh, n), np.float32), np.zeros((hh, n), np.float32),
                   np.zeros((hh, n), np.float32), np.zeros(hh, np.float32),
                   np.zeros(nsel, np.int64), np.zeros(nsel, np.int64),
                   np.zeros(nsel, np.float32), np.zeros(nsel, np.float32))


@njit(**_INL)
def spectra(scr):
    """(wr, wi, rr, ri, en, rm) of a :data:`Scratch`: W, R, the selection energies and their row maxima."""
    return scr.wr, scr.wi, scr.rr, scr.ri, scr.en, scr.rm


@njit(**_INL)
def coefficients(scr):
    """(sel_u, sel_v, sel_r, sel_i) of a :data:`Scratch`: the model's bins and coefficients."""
    return scr.sel_u, scr.sel_v, scr.sel_r, scr.sel_i


@njit(**_INL)
def gather(ctx, wp, blk, n, scr, joint):
    """Step 1 (fse-reference.md, weights), spatial weights w = s * rho^r and values f of the N x N support
    area centred on block ``blk`` = (by, bx, b, lvl), into scr.wbuf / scr.xbuf: s = 1 for known pixels,
    ``delta`` for reconstructed ones of this tile or of a tile of an earlier round (same-round tiles are
    never read), 0 for missing ones and outside; `joint` (a compile-time constant of the kernel):
    ``wp[y, x]`` for noisy measurements."""
    img = ctx.frame.img
    state = ctx.frame.state
    tile_round = ctx.plan.tile_round
    tshift = ctx.plan.tshift
    tw_tiles = ctx.plan.tw_tiles
    rho_tab = ctx.tab.rho_tab
    delta = ctx.par.delta
    wbuf = scr.wbuf
    xbuf = scr.xbuf
    by, bx, b, lvl = blk
    o = (n - b) // 2
    ay = by - o
    ax = bx - o
    t_self = (by >> tshift) * tw_tiles + (bx >> tshift)
    r_cur = tile_round[t_self]
    h, w = img.shape
    for i in range(n):
        y = ay + i
        # (direct 2-D indexing, no row views: a view costs an atomic reference-count update on the
        # array shared by all threads)
        if y < 0 or y >= h:
            for j in range(n):
                wbuf[i, j] = 0.0
                xbuf[i, j] = 0.0
            continue
        j0 = max(0, -ax)
        j1 = min(n, w - ax)
        for j in range(j0):
            wbuf[i, j] = 0.0
            xbuf[i, j] = 0.0
        for j in range(j1, n):
            wbuf[i, j] = 0.0
            xbuf[i, j] = 0.0
        tbase = (y >> tshift) * tw_tiles
        tsz = 1 << tshift
        tc0 = (ax + j0) >> tshift
        if ((ax + j1 - 1) >> tshift) - tc0 <= 2:
            # common case (window spans <= 3 tile columns): the same-round rule of the three columns
            # as selects, one branch-free pass over the row that vectorises
            d0 = np.float32(0.0)
            d1 = np.float32(0.0)
            d2 = np.float32(0.0)
            tt = tbase + tc0
            if tt == t_self or tile_round[tt] < r_cur:
                d0 = np.float32(delta)
            if tc0 + 1 < tw_tiles and (tt + 1 == t_self or tile_round[tt + 1] < r_cur):
                d1 = np.float32(delta)
            if tc0 + 2 < tw_tiles and (tt + 2 == t_self or tile_round[tt + 2] < r_cur):
                d2 = np.float32(delta)
            e0 = ((tc0 + 1) << tshift) - ax
            e1 = e0 + (1 << tshift)
            for jj in range(j0, j1):
                xx = ax + jj
                dwt = d0 if jj < e0 else (d1 if jj < e1 else d2)
                st = state[y, xx]
                fs = np.float32(1.0) if st == KNOWN else (dwt if st == RECONSTRUCTED else np.float32(0.0))
                if joint:
                    fs = wp[y, xx] if st == NOISY else fs
                wv = fs * rho_tab[lvl, i, jj]
                wbuf[i, jj] = wv
                xbuf[i, jj] = img[y, xx] if wv > 0.0 else np.float32(0.0)
            continue
        j = j0
        while j < j1:
            # one segment per tile column: the same-round rule is decided once per segment
            x = ax + j
            tt = tbase + (x >> tshift)
            allowed = tt == t_self or tile_round[tt] < r_cur
            dwt = np.float32(delta) if allowed else np.float32(0.0)
            je = min(j1, j + tsz - (x & (tsz - 1)))
            # branch-free (random masks make the state unpredictable): selects instead of branches
            for jj in range(j, je):
                xx = ax + jj
                st = state[y, xx]
                fs = np.float32(1.0) if st == KNOWN else (dwt if st == RECONSTRUCTED else np.float32(0.0))
                if joint:
                    fs = wp[y, xx] if st == NOISY else fs
                wv = fs * rho_tab[lvl, i, jj]
                wbuf[i, jj] = wv
                xbuf[i, jj] = img[y, xx] if wv > 0.0 else np.float32(0.0)
            j = je


@njit(**_INL)
def moments(wbuf, xbuf, n):
    """Step 2a: (sum w, sum w f, count, sum f, sum f^2) over the usable pixels of the area: a pure
    reduction pass (no stores), which vectorises."""
    sw = 0.0
    swf = 0.0
    cnt = 0.0
    s1 = 0.0
    s2 = 0.0
    for i in range(n):
        for j in range(n):
            wv = wbuf[i, j]
            fv = xbuf[i, j]
            sw += wv
            swf += wv * fv
            cnt += 1.0 if wv > 0.0 else 0.0
            s1 += fv
            s2 += fv * fv
    return sw, swf, cnt, s1, s2


@njit(**_INL)
def iteration_count(cnt, s1, s2, par):
    """Step 2b, texture-adaptive iteration count (Genser et al., IWSSIP 2017): clip(round(iter_c * sigma),
    iter_min, iter_max), sigma = (unweighted) std of the usable pixels relative to the data scale."""
    scale = par.scale
    iter_c = par.iter_c
    iter_min = par.iter_min
    iter_max = par.iter_max
    m1 = s1 / cnt
    var = s2 / cnt - m1 * m1
    if var < 0.0:
        var = 0.0
    sc = scale
    sigma = 0.0
    if sc > 0.0:
        sigma = math.sqrt(var) / sc
    nit = int(round(iter_c * sigma))
    if nit < iter_min:
        nit = iter_min
    if nit > iter_max:
        nit = iter_max
    return nit


@njit(**_INL)
def fft_pass(zb, off_r, off_i, n, tw_c, tw_s):
    """One 1-D radix-2 decimation-in-frequency FFT (Gentleman-Sande, in place, output in bit-reversed
    order) along the first index of the complex n x n block zb[off_r + p n + l] + i zb[off_i + p n + l],
    batched over the n lanes l: every butterfly is a contiguous, vectorised loop over the lanes. One
    flat buffer with compile-time offsets (n = 16) lets LLVM prove that the rows do not alias."""
    half = n // 2
    step = 1
    while half >= 1:
        for start in range(0, n, 2 * half):
            for k in range(half):
                p = (start + k) * n
                q = p + half * n
                c = tw_c[k * step]      # e^{-i 2 pi k step / n} = c - i s
                s = tw_s[k * step]
                for l in range(n):
                    ar = zb[off_r + p + l]
                    ai = zb[off_i + p + l]
                    br = zb[off_r + q + l]
                    bi = zb[off_i + q + l]
                    zb[off_r + p + l] = ar + br
                    zb[off_i + p + l] = ai + bi
                    dr = ar - br
                    di = ai - bi
                    zb[off_r + q + l] = dr * c + di * s
                    zb[off_i + q + l] = di * c - dr * s
        half //= 2
        step *= 2


@njit(**_INL)
def pack_scale(cnt, s1, s2):
    """(2^-e, 2^e) with 2^e ~ the std of the usable values (from :func:`moments`; 1 when they are
    constant): w (f - mean) 2^-e is of the magnitude of w, exactly (a power of two), so a k-fold
    scaled input (k a power of two) gives the same packed FFT, and any k the same up to rounding."""
    m1 = s1 / cnt
    var = s2 / cnt - m1 * m1
    e = 0
    if var > 0.0:
        e = math.frexp(math.sqrt(var))[1]
    return np.float32(math.ldexp(1.0, -e)), np.float32(math.ldexp(1.0, e))


@njit(**_INL)
def split_bin(zb, n, ia, ib, vu, hx, prior2, scr):
    """One bin (v, u) = ``vu`` of the split of Z = DFT(w + i x) (zb[2n^2 + .] real, zb[3n^2 + .]
    imaginary, ia: k, ib: -k): W = (Z(k) + conj Z(-k)) / 2 into its copies on the doubled periodic grid
    (rows v and, for v < n/2 + 1, v + n; columns u and u + n); for v < n/2 + 1 also
    R = (Z(k) - conj Z(-k)) / 2i (times 2 hx = the packing's inverse scale) and its selection energy
    |R|^2 prior^2."""
    v, u = vu
    wr, wi, rr, ri, en, _rm = spectra(scr)
    nn = n * n
    ar = zb[2 * nn + ia]
    ai = zb[3 * nn + ia]
    br = zb[2 * nn + ib]
    bi = zb[3 * nn + ib]
    wre = np.float32(0.5) * (ar + br)
    wim = np.float32(0.5) * (ai - bi)
    wr[v, u] = wre
    wi[v, u] = wim
    wr[v, u + n] = wre
    wi[v, u + n] = wim
    if 2 * v <= n:
        wr[v + n, u] = wre
        wi[v + n, u] = wim
        wr[v + n, u + n] = wre
        wi[v + n, u + n] = wim
        rre = hx * (ai + bi)
        rim = hx * (br - ar)
        rr[v, u] = rre
        ri[v, u] = rim
        en[v, u] = (rre * rre + rim * rim) * prior2[v, u]


@njit(**_INL)
def forward_dft(n, tab, scr, xi):
    """Step 3 (fse-reference.md, spectra), W = DFT(w) and R = DFT(w (f - mean)) from zb[0:n^2] = w and
    zb[n^2:2n^2] = w (f - mean) / xi (row-major [i, j]; xi a power of two, :func:`pack_scale`) straight
    into the layout of the iterations: R[v, u] (v = half-spectrum index, u full, contiguous) with its
    selection energies |R|^2 prior^2 and their per-row maxima; W on a doubled periodic grid W[v', u'] so
    that W(j - k) and W(j + k) are contiguous slices without modulo (rows >= n + n/2 + 1 are never read
    and not written). Both signals are real: one complex 2-D FFT of z = w + i w (f - mean), split by
    conjugate symmetry, W(k) = (Z(k) + conj Z(-k)) / 2, R(k) = (Z(k) - conj Z(-k)) / 2i. The FFT is
    batched radix-2 over the rows (lanes: the columns), a transpose that also undoes the bit reversal of
    the row frequencies, then over the columns (lanes: the row frequencies u, natural order)."""
    tw_c = tab.tw_c
    tw_s = tab.tw_s
    bitrev = tab.bitrev
    prior2 = tab.prior2
    zb = scr.zb
    nn = n * n
    hx = np.float32(0.5) * xi
    fft_pass(zb, 0, nn, n, tw_c, tw_s)              # along i: row p holds u = bitrev[p]
    for p in range(n):
        bp = bitrev[p]
        for j in range(n):
            zb[2 * nn + j * n + bp] = zb[p * n + j]
            zb[3 * nn + j * n + bp] = zb[nn + p * n + j]
    fft_pass(zb, 2 * nn, 3 * nn, n, tw_c, tw_s)     # along j: Z(u, v) at [bitrev[v], u]
    for v in range(n):
        ra = bitrev[v] * n
        rb = bitrev[(n - v) & (n - 1)] * n
        split_bin(zb, n, ra, rb, (v, 0), hx, prior2, scr)
        for u in range(1, n):
            split_bin(zb, n, ra + u, rb + n - u, (v, u), hx, prior2, scr)
    row_maxima(n, scr.en, scr.rm)


@njit(**_INL)
def row_maxima(n, en, rm):
    """rm[v] = max_u en[v, u] with four independent running maxima (n is a multiple of 4): a single
    chain of scalar max operations is latency-bound and keeps the update loop from vectorising. The
    maximum is exact."""
    hh = n // 2 + 1
    for v in range(hh):
        m0 = en[v, 0]
        m1 = en[v, 1]
        m2 = en[v, 2]
        m3 = en[v, 3]
        for u in range(4, n, 4):
            m0 = max(m0, en[v, u])
            m1 = max(m1, en[v, u + 1])
            m2 = max(m2, en[v, u + 2])
            m3 = max(m3, en[v, u + 3])
        rm[v] = max(max(m0, m1), max(m2, m3))


@njit(**_INL)
def select_bin(n, en, rm):
    """Step 4a (fse-reference.md, iterations), basis choice: the half-spectrum bin (kv, ku) of the largest
    weighted residual energy |R(k)|^2 prior(k)^2 (per-row maxima first, then the row); best = that energy."""
    hh = n // 2 + 1
    kv = 0
    best = rm[0]
    for v in range(1, hh):
        if rm[v] > best:
            best = rm[v]
            kv = v
    ku = 0
    for u in range(n):
        if en[kv, u] == best:
            ku = u
            break
    return kv, ku, best


@njit(**_INL)
def update_self(n, kv, ku, cr, prior2, scr):
    """Step 4b for a self-conjugate bin (DC, Nyquist): R(j) -= c W(j - k), c real; energies refreshed."""
    wr, wi, rr, ri, en, rm = spectra(scr)
    hh = n // 2 + 1
    u1 = n - ku
    for v in range(hh):
        v1 = v - kv + n
        for u in range(n):
            nr = rr[v, u] - cr * wr[v1, u1 + u]
            ni = ri[v, u] - cr * wi[v1, u1 + u]
            rr[v, u] = nr
            ri[v, u] = ni
            en[v, u] = (nr * nr + ni * ni) * prior2[v, u]
    row_maxima(n, en, rm)


@njit(**_INL)
def update_pair(n, kv, ku, cr, ci, prior2, scr):
    """Step 4b for a conjugate pair, in the frequency domain without an inverse FFT:
    R(j) -= c W(j - k) + conj(c) W(j + k) (= DFT(w (f - g)) exactly); energies refreshed."""
    wr, wi, rr, ri, en, rm = spectra(scr)
    hh = n // 2 + 1
    u1 = n - ku
    for v in range(hh):
        v1 = v - kv + n
        v2 = v + kv
        for u in range(n):
            a = wr[v1, u1 + u]
            bq = wi[v1, u1 + u]
            a2 = wr[v2, ku + u]
            b2 = wi[v2, ku + u]
            nr = rr[v, u] - (cr * (a + a2) + ci * (b2 - bq))
            ni = ri[v, u] - (cr * (bq + b2) + ci * (a - a2))
            rr[v, u] = nr
            ri[v, u] = ni
            en[v, u] = (nr * nr + ni * ni) * prior2[v, u]
    row_maxima(n, en, rm)


@njit(**_INL)
def extrapolate(n, nit, gamma, prior2, scr):
    """Step 4 (fse-reference.md, iterations): choose the basis function (bin) of largest weighted
    residual energy, its coefficient c = gamma R(k) / W(0) (gamma: orthogonality-deficiency compensation),
    add c at k and conj(c) at -k to the model (a pair counts 2 iterations, DC / Nyquist 1), update the
    residual spectrum. The model's coefficients go to scr.sel_*; returns their count."""
    wr, _wi, rr, ri, en, rm = spectra(scr)
    sel_u, sel_v, sel_r, sel_i = coefficients(scr)
    w0 = wr[0, 0]
    g = np.float32(gamma) / w0
    it = 0
    ns = 0
    while it < nit:
        kv, ku, best = select_bin(n, en, rm)
        if best <= 0.0:
            break
        cr = rr[kv, ku] * g
        ci = ri[kv, ku] * g
        selfm = ((ku == 0) or (2 * ku == n)) and ((kv == 0) or (2 * kv == n))
        if selfm:
            ci = np.float32(0.0)
            update_self(n, kv, ku, cr, prior2, scr)
            it += 1
        else:
            update_pair(n, kv, ku, cr, ci, prior2, scr)
            it += 2
        sel_u[ns] = ku
        sel_v[ns] = kv
        sel_r[ns] = cr if selfm else 2.0 * cr
        sel_i[ns] = ci if selfm else 2.0 * ci
        ns += 1
    return ns


@njit(**_INL)
def synthesize(b, lvl, ns, phs, scr):
    """Step 5 (fse-reference.md, synthesis), the model on the block only: g(m) - mean = sum Re(c e^{+i 2
    pi k m / N}) into scr.xbuf[:b, :b] (no inverse FFT). Separable phases: Re(c e^{i(a + b)}) = cos b (c_r
    cos a - c_i sin a) - sin b (c_r sin a + c_i cos a), a = 2 pi u (o + i) / N per row, b = 2 pi v (o + j)
    / N per column, read from the block size's phase table (``Tables.phs``), vectorised over the block row."""
    sel_u, sel_v, sel_r, sel_i = coefficients(scr)
    xbuf = scr.xbuf
    for i in range(b):
        for j in range(b):
            xbuf[i, j] = 0.0
    for q in range(ns):
        cq = sel_r[q]
        sq = sel_i[q]
        uq = sel_u[q]
        vq = sel_v[q]
        for i in range(b):
            ca = phs[lvl, 0, uq, i]
            sa = phs[lvl, 1, uq, i]
            pp = cq * ca - sq * sa
            qq = cq * sa + sq * ca
            for j in range(b):
                xbuf[i, j] += pp * phs[lvl, 0, vq, j] - qq * phs[lvl, 1, vq, j]


@njit(**_INL)
def write_block(frame, mest, par, blk, mean, xbuf, joint):
    """Step 6, the block's missing pixels only: mean + model, clamped to [lo, hi] where bounded, become
    reconstructed (weight delta) for later blocks; known pixels stay bit-exact. `joint`: the model at
    noisy measurements (which stay measurements for later blocks) goes to ``mest``. A block inside the
    image is written branch-free (random masks make ``state`` unpredictable): every pixel is stored, a
    known or skipped one with its own value and state (no other thread writes this block)."""
    img = frame.img
    state = frame.state
    lo = frame.lo
    hi = frame.hi
    use_lo = par.use_lo
    use_hi = par.use_hi
    by, bx, b, _lvl = blk
    h, w = img.shape
    if not joint and by + b <= h and bx + b <= w:
        for i in range(b):
            y = by + i
            for j in range(b):
                x = bx + j
                st = state[y, x]
                val = np.float32(mean + xbuf[i, j])
                if use_lo:
                    val = max(val, lo[y, x])
                if use_hi:
                    val = min(val, hi[y, x])
                miss = st == MISSING
                img[y, x] = val if miss else img[y, x]
                state[y, x] = np.uint8(RECONSTRUCTED) if miss else st
        return
    for i in range(b):
        y = by + i
        if y >= h:
            break
        for j in range(b):
            x = bx + j
            if x >= w:
                break
            st = state[y, x]
            if st != MISSING:
                if joint and st == NOISY:
                    val = np.float32(mean + xbuf[i, j])
                    if use_lo and val < lo[y, x]:
                        val = lo[y, x]
                    if use_hi and val > hi[y, x]:
                        val = hi[y, x]
                    mest[y, x] = val
                continue
            val = np.float32(mean + xbuf[i, j])
            if use_lo and val < lo[y, x]:
                val = lo[y, x]
            if use_hi and val > hi[y, x]:
                val = hi[y, x]
            img[y, x] = val
            state[y, x] = RECONSTRUCTED


def make_block_kernel(n_fixed, joint=False):
    """The block kernel, FSE of one quadtree leaf; ``n_fixed`` > 0: specialised for that window size (a
    compile-time constant), 0: the window size of the tables. ``joint`` (compile-time): noisy
    measurements enter the fit with the weights ``wp`` and the model there is written to ``mest``
    (joint estimation, docs/FSE.md); without it ``noisy`` is never read."""

    @njit(cache=True, nogil=True, fastmath=True)
    def block_kernel(ctx, noisy, li, scr):
        """Reconstruct the missing pixels of leaf ``li`` of ``ctx.plan`` in place (Seiler & Kaup, SPL 2010:
        weighted projection of the support area onto DFT basis functions, one chosen per iteration,
        residual updated in the frequency domain). ``noisy`` = (wp, mest). Returns False if its support
        area has no usable pixel (left for the fallback)."""
        n = n_fixed if n_fixed > 0 else ctx.tab.tw_c.shape[0]
        lvl = ctx.plan.leaf_lvl[li]
        b = ctx.tab.sizes[lvl]
        blk = (ctx.plan.leaf_y[li], ctx.plan.leaf_x[li], b, lvl)
        gather(ctx, noisy[0], blk, n, scr, joint)
        wbuf = scr.wbuf
        xbuf = scr.xbuf
        zb = scr.zb
        sw, swf, cnt, s1, s2 = moments(wbuf, xbuf, n)
        if sw <= 0.0:
            return False
        mean = swf / sw     # weighted mean removed (translation invariance, float32 conditioning)
        nit = iteration_count(cnt, s1, s2, ctx.par)
        fm = np.float32(mean)
        # w and w (f - mean) share one complex FFT (forward_dft): the second is brought to the first's
        # magnitude by a power of two 2^-e ~ 1 / std(f) (exact, undone in the split), so that the
        # rounding of one does not swamp the other whatever the data scale (scale invariance)
        xs, xi = pack_scale(cnt, s1, s2)
        nn = n * n
        for i in range(n):
            for j in range(n):
                wv = wbuf[i, j]
                zb[i * n + j] = wv
                zb[nn + i * n + j] = wv * (xbuf[i, j] - fm) * xs
        forward_dft(n, ctx.tab, scr, xi)
        ns = extrapolate(n, nit, ctx.par.gamma, ctx.tab.prior2, scr)
        synthesize(b, lvl, ns, ctx.tab.phs, scr)
        write_block(ctx.frame, noisy[1], ctx.par, blk, mean, xbuf, joint)
        return True

    return block_kernel


# the common 16 x 16 window (preview, fast, balanced), the 32 x 32 one (best; fast / balanced when few
# pixels are known) and any other window; the joint estimation's own specialisations
block16 = make_block_kernel(16)
block32 = make_block_kernel(32)
block_generic = make_block_kernel(0)
block16_joint = make_block_kernel(16, True)
block_joint = make_block_kernel(0, True)
