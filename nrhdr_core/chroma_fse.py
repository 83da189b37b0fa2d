"""Colour differences by green-guided FSE at full resolution (docs/COLOUR.md "False colour").

A colour difference d (log2 of a channel over green), known at the known photosites of its channel (a lattice
of every other row and column, parity py, px), is extrapolated to every photosite by FSE (Seiler and Kaup
2010; fse-reference.md "The model, one block at a time": spatial weight rho^r, the weighted mean removed,
basis selection with the spectral prior, coefficient gamma R(k) / W(0), residual update in the frequency
domain, fixed iteration count), one B x B block at a time in an N x N support area of the full photosite grid.

Guided selection (joint sparsity of the channels, after the inter-channel model of Backes and Froehlich
2020): bins k and k + p fit the known samples alike where the DFT W of the area's weights peaks at p
(|W(p)| >= TAU W(0): p = (N/2, 0), (0, N/2), (N/2, N/2) of the lattice, and the peaks of a regular pattern
of known photosites on it; aliases). Each bin's selection weight is the prior times ((S(k) + e) / (max of S
over k and its aliases + e))^ALPHA, S = |DFT| of the windowed log green around its weighted mean,
e = EPS x max S: colour detail that follows luminance detail is taken at green's frequency, also beyond the
lattice's Nyquist limit (up to KMAX), an alias at a frequency green does not show is not.

Synthesis: the model's components within the lattice's band (|k| <= N/4 in both directions) are evaluated at
the lattice sites (at a known site: d less the other components) and interpolated bilinearly, as a lattice
would be; the components beyond the band are added where they are: a colour step in d stays free of the
band-limited interpolation's ringing.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

N = 32              # support area (FFT window)
B = 4               # block
RHO = 0.66          # spatial weight decay per pixel for B = 4 (fse-reference.md)
GAMMA = 0.5         # orthogonality-deficiency compensation
ITERS = 30          # iterations (a conjugate pair is one)
ALPHA = 2.0         # exponent of the alias-group guide
EPS = 0.02          # guide floor, relative to the area's largest green magnitude
TAU = 0.9           # an alias shift p: |W(p)| >= TAU W(0), W the DFT of the area's weights
KMAX = 0.4          # no component beyond this radial frequency (cycles/photosite)
MAX_PEAKS = 16      # more alias shifts than this: the guide relative to the area's largest magnitude


def _tables():
    """(rho^r weights (N, N), cos and sin of 2 pi t / N, the spectral prior 1 - sqrt(2) |k| / N on the
    full spectrum (N, N)) as float32."""
    yy, xx = np.mgrid[0:N, 0:N]
    c0 = (N - 1) / 2.0
    rw = RHO ** np.sqrt((yy - c0) ** 2 + (xx - c0) ** 2)
    t = np.arange(N)
    f = np.fft.fftfreq(N)
    kr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    prior = np.where(kr <= KMAX, np.clip(1.0 - np.sqrt(2.0) * kr, 0.0, 1.0), 0.0)
    return (rw.astype(np.float32), np.cos(2 * np.pi * t / N).astype(np.float32),
            np.sin(2 * np.pi * t / N).astype(np.float32), prior.astype(np.float32))


def guided_fse(d, known, guide, py, px, out=None) -> np.ndarray:
    """float32 (H, W): `d` (float, read where `known`, on the lattice of rows py, py + 2, ... and columns
    px, px + 2, ...) extrapolated to every photosite by the green-guided FSE of the module docstring;
    `guide`: float (H, W), the log green plane; known photosites keep d."""
    if py not in (0, 1) or px not in (0, 1):
        raise ValueError(f"guided_fse: the lattice's parities py, px must be 0 or 1, got {py}, {px}")
    d = np.ascontiguousarray(d, np.float32)
    g = np.ascontiguousarray(guide, np.float32)
    k = np.ascontiguousarray(known, np.bool_)
    if d.shape != k.shape or d.shape != g.shape or d.ndim != 2:
        raise ValueError(f"guided_fse: d, known and guide must be 2-D of one shape, got {d.shape}, {k.shape}, "
                         f"{g.shape}")
    if out is None:
        out = np.empty(d.shape, np.float32)
    rw, cs, sn, prior = _tables()
    ut = np.outer(np.arange(N), np.arange(N)) % N
    _guided(d, k, g, py, px, rw, cs, sn, cs[ut], sn[ut], prior, np.float32(GAMMA), ITERS, np.float32(ALPHA),
            np.float32(EPS), np.float32(TAU), B, out)
    return out


@njit(cache=True, nogil=True, fastmath=True)
def _dft_half(x, cs, sn, ec, es, tr, ti, xr, xi):
    """(xr, xi)[v, u] = DFT of the real N x N x for u <= N/2 (ec, es: cos and sin of 2 pi u j / N; tr, ti:
    row-pass scratch)."""
    n = x.shape[0]
    hh = n // 2 + 1
    for i in range(n):
        for u in range(hh):
            sr = np.float32(0.0)
            si = np.float32(0.0)
            for j in range(n):
                sr += x[i, j] * ec[u, j]
                si -= x[i, j] * es[u, j]
            tr[i, u] = sr
            ti[i, u] = si
    for v in range(n):
        for u in range(hh):
            xr[v, u] = 0.0
            xi[v, u] = 0.0
        for i in range(n):
            t = (v * i) % n
            c = cs[t]
            s = sn[t]
            for u in range(hh):
                xr[v, u] += tr[i, u] * c + ti[i, u] * s
                xi[v, u] += ti[i, u] * c - tr[i, u] * s


@njit(cache=True, nogil=True, fastmath=True)
def _full(hr, hi, fr, fi):
    """The full spectrum (fr, fi) (N, N) of a real signal from its half (hr, hi) (u <= N/2)."""
    n = fr.shape[0]
    hh = n // 2 + 1
    for v in range(n):
        for u in range(n):
            if u < hh:
                fr[v, u] = hr[v, u]
                fi[v, u] = hi[v, u]
            else:
                fr[v, u] = hr[(n - v) % n, n - u]
                fi[v, u] = -hi[(n - v) % n, n - u]


@njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _guided(d, known, guide, py, px, rw, cs, sn, ec, es, prior, gamma, iters, alpha, eps, tau, b, out):
    """`guided_fse` over every block, block rows in parallel."""
    h, w = d.shape
    n = rw.shape[0]
    hh = n // 2 + 1
    o = (n - b) // 2
    nby = (h + b - 1) // b
    for by in prange(nby):
        wb = np.zeros((n, n), np.float32)
        xb = np.zeros((n, n), np.float32)
        gb = np.zeros((n, n), np.float32)
        tr = np.zeros((n, hh), np.float32)
        ti = np.zeros((n, hh), np.float32)
        whr = np.zeros((n, hh), np.float32)
        whi = np.zeros((n, hh), np.float32)
        wr = np.zeros((n, n), np.float32)
        wi = np.zeros((n, n), np.float32)
        rr = np.zeros((n, hh), np.float32)
        ri = np.zeros((n, hh), np.float32)
        sr = np.zeros((n, hh), np.float32)
        si = np.zeros((n, hh), np.float32)
        sf = np.zeros((n, n), np.float32)
        sfi = np.zeros((n, n), np.float32)
        pr = np.zeros((n, hh), np.float32)
        ib = np.zeros((b + 2, b + 2), np.float32)
        ob = np.zeros((b + 2, b + 2), np.float32)
        pk_v = np.zeros(MAX_PEAKS, np.int64)
        pk_u = np.zeros(MAX_PEAKS, np.int64)
        sel_v = np.zeros(iters, np.int64)
        sel_u = np.zeros(iters, np.int64)
        sel_r = np.zeros(iters, np.float32)
        sel_i = np.zeros(iters, np.float32)
        y0 = by * b
        for bx in range(0, w, b):
            ay = y0 - o
            ax = bx - o
            sw = np.float32(0.0)
            sg = np.float32(0.0)
            sd = np.float32(0.0)
            srw = np.float32(0.0)
            for i in range(n):
                y = ay + i
                yc = min(max(y, 0), h - 1)
                for j in range(n):
                    x = ax + j
                    xc = min(max(x, 0), w - 1)
                    inside = (y == yc) and (x == xc)
                    kk = inside and known[yc, xc]
                    wv = rw[i, j] if kk else np.float32(0.0)
                    wb[i, j] = wv
                    xb[i, j] = wv * d[yc, xc] if kk else np.float32(0.0)
                    gb[i, j] = rw[i, j] * guide[yc, xc]
                    sw += wv
                    sd += xb[i, j]
                    sg += gb[i, j]
                    srw += rw[i, j]
            hb = min(b, h - y0)
            wbk = min(b, w - bx)
            if sw <= 0.0:
                for i in range(hb):
                    for j in range(wbk):
                        out[y0 + i, bx + j] = d[y0 + i, bx + j] if known[y0 + i, bx + j] else np.float32(0.0)
                continue
            gm = sg / srw
            dm = sd / sw
            for i in range(n):
                for j in range(n):
                    gb[i, j] -= gm * rw[i, j]
                    xb[i, j] -= dm * wb[i, j]
            _dft_half(wb, cs, sn, ec, es, tr, ti, whr, whi)
            _full(whr, whi, wr, wi)
            _dft_half(xb, cs, sn, ec, es, tr, ti, rr, ri)
            _dft_half(gb, cs, sn, ec, es, tr, ti, sr, si)
            smax = np.float32(0.0)
            for v in range(n):
                for u in range(hh):
                    m = np.sqrt(sr[v, u] * sr[v, u] + si[v, u] * si[v, u])
                    sr[v, u] = m
                    smax = max(smax, m)
            for v in range(n):
                for u in range(n):
                    if u < hh:
                        sf[v, u] = sr[v, u]
                    else:
                        sf[v, u] = sr[(n - v) % n, n - u]
            e = eps * smax + np.float32(1e-30)
            w0 = wr[0, 0]
            lim = tau * tau * w0 * w0
            npk = 0
            for v in range(n):
                for u in range(n):
                    if npk < MAX_PEAKS and wr[v, u] * wr[v, u] + wi[v, u] * wi[v, u] >= lim:
                        pk_v[npk] = v
                        pk_u[npk] = u
                        npk += 1
                    elif wr[v, u] * wr[v, u] + wi[v, u] * wi[v, u] >= lim:
                        npk += 1
            for v in range(n):
                for u in range(hh):
                    g4 = smax
                    if npk <= MAX_PEAKS:
                        g4 = sf[v, u]
                        for p in range(npk):
                            g4 = max(g4, sf[(v + pk_v[p]) % n, (u + pk_u[p]) % n])
                    q = (sf[v, u] + e) / (g4 + e)
                    pr[v, u] = prior[v, u] * q ** alpha
            pr[0, 0] = prior[0, 0]
            for it in range(iters):
                best = np.float32(-1.0)
                kv = 0
                ku = 0
                for v in range(n):
                    for u in range(hh):
                        a = (rr[v, u] * rr[v, u] + ri[v, u] * ri[v, u]) * pr[v, u] * pr[v, u]
                        if a > best:
                            best = a
                            kv = v
                            ku = u
                cr = gamma * rr[kv, ku] / w0
                ci = gamma * ri[kv, ku] / w0
                mv = (n - kv) % n
                mu = (n - ku) % n
                self_c = (mv == kv) and (mu == ku)
                if self_c:
                    ci = np.float32(0.0)
                sel_v[it] = kv
                sel_u[it] = ku
                sel_r[it] = cr
                sel_i[it] = ci
                for v in range(n):
                    av = (v - kv) % n
                    bv = (v + kv) % n
                    for u in range(hh):
                        au = (u - ku) % n
                        bu = (u + ku) % n
                        # c W(j - k) (+ conj(c) W(j + k) for a pair)
                        xr_ = cr * wr[av, au] - ci * wi[av, au]
                        xi_ = cr * wi[av, au] + ci * wr[av, au]
                        if not self_c:
                            xr_ += cr * wr[bv, bu] + ci * wi[bv, bu]
                            xi_ += cr * wi[bv, bu] - ci * wr[bv, bu]
                        rr[v, u] -= xr_
                        ri[v, u] -= xi_
            # the model on the block's (b + 2) x (b + 2) surround: the lattice band (|k| <= N/4 in both
            # directions) into ib, the components beyond it into ob
            q4 = n // 4
            for i in range(b + 2):
                for j in range(b + 2):
                    pi_ = o - 1 + i
                    pj = o - 1 + j
                    ai = dm
                    ao = np.float32(0.0)
                    for it in range(iters):
                        sv = sel_v[it]
                        su = sel_u[it]
                        t = (sv * pi_ + su * pj) % n
                        re = sel_r[it] * cs[t] - sel_i[it] * sn[t]     # Re(c e^{i theta})
                        self_b = ((n - sv) % n == sv) and ((n - su) % n == su)
                        re = re if self_b else np.float32(2.0) * re
                        inband = min(sv, n - sv) <= q4 and min(su, n - su) <= q4
                        ai += re if inband else np.float32(0.0)
                        ao += np.float32(0.0) if inband else re
                    yy = y0 - 1 + i
                    xx = bx - 1 + j
                    if 0 <= yy < h and 0 <= xx < w and known[yy, xx]:
                        ai = d[yy, xx] - ao             # the lattice band exact at a known site
                    ib[i, j] = ai
                    ob[i, j] = ao
            for i in range(hb):
                for j in range(wbk):
                    y = y0 + i
                    x = bx + j
                    if known[y, x]:
                        out[y, x] = d[y, x]
                        continue
                    # the lattice band bilinear from the lattice's sites (rows and columns of parity py, px)
                    ra = i + 1 if (y & 1) == py else i
                    rb = i + 1 if (y & 1) == py else i + 2
                    ca = j + 1 if (x & 1) == px else j
                    cb = j + 1 if (x & 1) == px else j + 2
                    lin = np.float32(0.25) * (ib[ra, ca] + ib[ra, cb] + ib[rb, ca] + ib[rb, cb])
                    out[y, x] = lin + ob[i + 1, j + 1]
    return out
