"""Colour differences by green-guided FSE at full resolution (docs/COLOUR.md "False colour").

A colour difference d (log2 of a channel over green), known at the known photosites of its channel (a lattice
of every other row and column, parity py, px), is extrapolated to every photosite by FSE (Seiler and Kaup
2010; fse-reference.md "The model, one block at a time": spatial weight rho^r, the weighted mean removed,
basis selection with the spectral prior, coefficient gamma R(k) / W(0), residual update in the frequency
domain, fixed iteration count), one B x B block at a time in an N x N support area of the full photosite grid.
The known samples lie on the lattice, so the area's weighted residual is an (N/2 x N/2) lattice signal: its
spectrum on the full grid is R(k) = e^{-2 pi i k.q / N} R_L(k mod N/2) (q: the lattice's offset in the area),
and the residual update R(j) -= c W(j - k) + conj(c) W(j + k) holds for R_L, W_L with c e^{2 pi i k.q / N}:
the iterations run on the N/2 x N/2 lattice spectrum (a quarter of the bins), the selected bin k among its
aliases being the one of largest selection weight (they share |R|). Spectra by radix-2 FFT
(`fse.kernel.fft_pass`); the green spectrum of an area serves both channels, two areas' in one complex FFT.

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

from .fse.kernel import fft_pass

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
    full spectrum (N, N), the bit-reversed orders of N and N/2) as float32 / int64."""
    yy, xx = np.mgrid[0:N, 0:N]
    c0 = (N - 1) / 2.0
    rw = RHO ** np.sqrt((yy - c0) ** 2 + (xx - c0) ** 2)
    t = np.arange(N)
    f = np.fft.fftfreq(N)
    kr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    prior = np.where(kr <= KMAX, np.clip(1.0 - np.sqrt(2.0) * kr, 0.0, 1.0), 0.0)

    def bitrev(n):
        bits = n.bit_length() - 1
        return np.array([int(format(i, f"0{bits}b")[::-1], 2) for i in range(n)], np.int64)
    return (rw.astype(np.float32), np.cos(2 * np.pi * t / N).astype(np.float32),
            np.sin(2 * np.pi * t / N).astype(np.float32), prior.astype(np.float32), bitrev(N), bitrev(N // 2))


def guided_fse(d, known, guide, py, px, out=None) -> np.ndarray:
    """float32 (H, W): `d` (float, read where `known`, on the lattice of rows py, py + 2, ... and columns
    px, px + 2, ...) extrapolated to every photosite by the green-guided FSE of the module docstring;
    `guide`: float (H, W), the log green plane; known photosites keep d. With `d`, `known` of shape (C, H, W)
    and py, px sequences of C parities: C channels in one pass (the guide's spectrum computed once per area),
    `out` (C, H, W)."""
    d = np.asarray(d)
    one = d.ndim == 2
    pys, pxs = ((py,), (px,)) if one else (tuple(py), tuple(px))
    for a, b_ in zip(pys, pxs):
        if a not in (0, 1) or b_ not in (0, 1):
            raise ValueError(f"guided_fse: the lattice's parities py, px must be 0 or 1, got {a}, {b_}")
    d3 = np.ascontiguousarray(d[None] if one else d, np.float32)
    k3 = np.ascontiguousarray(np.asarray(known)[None] if one else known, np.bool_)
    g = np.ascontiguousarray(guide, np.float32)
    if d3.ndim != 3 or d3.shape != k3.shape or d3.shape[1:] != g.shape or len(pys) != d3.shape[0]:
        raise ValueError(f"guided_fse: d, known (and py, px per channel) and guide must be of one shape, got "
                         f"{d.shape}, {np.shape(known)}, {g.shape}")
    for c, (a, b_) in enumerate(zip(pys, pxs)):
        if k3[c].sum() != k3[c, a::2, b_::2].sum():
            raise ValueError(f"guided_fse: known photosites off the lattice of parities {a}, {b_}")
    if out is None:
        out = np.empty(d.shape, np.float32)
    o3 = out[None] if one else out
    rw, cs, sn, prior, br, brl = _tables()
    par = np.array([pys, pxs], np.int64).T.copy()
    _guided(d3, k3, g, par, rw, cs, sn, prior, br, brl, np.float32(GAMMA), ITERS, np.float32(ALPHA),
            np.float32(EPS), np.float32(TAU), B, o3)
    return out


@njit(cache=True, nogil=True, fastmath=True)
def _fft2(zb, n, tw_c, tw_s, br):
    """The 2-D DFT of the complex n x n block zb[0:n^2] + i zb[n^2:2n^2] (row-major [i, j]) by
    `fse.kernel.fft_pass` along i, a transpose that undoes the bit reversal, then along j: Z(v, u) at
    zb[2n^2 + br[u] n + v] + i zb[3n^2 + br[u] n + v] (tw_c, tw_s: cos and sin of 2 pi t / n)."""
    nn = n * n
    fft_pass(zb, 0, nn, n, tw_c, tw_s)
    for p in range(n):
        bp = br[p]
        for j in range(n):
            zb[2 * nn + j * n + bp] = zb[p * n + j]
            zb[3 * nn + j * n + bp] = zb[nn + p * n + j]
    fft_pass(zb, 2 * nn, 3 * nn, n, tw_c, tw_s)


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _pair(zb, n, br, v, u):
    """(Re, Im) of Z(v, u) and of Z(-v, -u) from `_fft2`'s output layout."""
    nn = n * n
    a = 2 * nn + br[u] * n + v
    b = 2 * nn + br[(n - u) & (n - 1)] * n + ((n - v) & (n - 1))
    return zb[a], zb[a + nn], zb[b], zb[b + nn]


@njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _guided(d, known, guide, par, rw, cs, sn, prior, br, brl, gamma, iters, alpha, eps, tau, b, out):
    """`guided_fse` over every block and channel, block rows in parallel."""
    nc, h, w = d.shape
    n = rw.shape[0]
    nn = n * n
    m = n // 2                  # the lattice's spectrum
    mm = m * m
    mh = m // 2 + 1
    o = (n - b) // 2
    q4 = n // 4
    nby = (h + b - 1) // b
    csl = np.empty(m, np.float32)
    snl = np.empty(m, np.float32)
    for t in range(m):
        csl[t] = cs[2 * t]
        snl[t] = sn[2 * t]
    for by in prange(nby):
        zg = np.zeros(4 * nn, np.float32)
        zl = np.zeros(4 * mm, np.float32)
        sfs = np.zeros((2, n, n), np.float32)
        wr = np.zeros((2 * m, 2 * m), np.float32)
        wi = np.zeros((2 * m, 2 * m), np.float32)
        rr = np.zeros((m, mh), np.float32)
        ri = np.zeros((m, mh), np.float32)
        gmxs = np.zeros((2, m, m), np.float32)
        smx = np.zeros(2, np.float32)
        pb = np.zeros((m, mh), np.float32)
        al_v = np.zeros((m, mh), np.int64)
        al_u = np.zeros((m, mh), np.int64)
        ib = np.zeros((b + 2, b + 2), np.float32)
        ob = np.zeros((b + 2, b + 2), np.float32)
        pk_v = np.zeros(MAX_PEAKS, np.int64)
        pk_u = np.zeros(MAX_PEAKS, np.int64)
        sel_v = np.zeros(iters, np.int64)
        sel_u = np.zeros(iters, np.int64)
        sel_r = np.zeros(iters, np.float32)
        sel_i = np.zeros(iters, np.float32)
        sel_b = np.zeros(iters, np.bool_)
        y0 = by * b
        hb = min(b, h - y0)
        for bx in range(0, w, b):
            ay = y0 - o
            ax = bx - o
            wbk = min(b, w - bx)
            # the guide: |DFT| of the windowed log green around its weighted mean, once for all channels; the
            # areas of two neighbouring blocks as one complex FFT (real and imaginary part), split by conjugate
            # symmetry
            half = (bx // b) & 1
            if half == 0:
                for hf in range(2):
                    sg = np.float32(0.0)
                    srw = np.float32(0.0)
                    off = hf * nn
                    ax2 = ax + hf * b
                    for i in range(n):
                        yc = min(max(ay + i, 0), h - 1)
                        for j in range(n):
                            xc = min(max(ax2 + j, 0), w - 1)
                            zg[off + i * n + j] = rw[i, j] * guide[yc, xc]
                            sg += zg[off + i * n + j]
                            srw += rw[i, j]
                    gm = sg / srw
                    for i in range(n):
                        for j in range(n):
                            zg[off + i * n + j] -= gm * rw[i, j]
                _fft2(zg, n, cs, sn, br)
                smx[0] = np.float32(0.0)
                smx[1] = np.float32(0.0)
                for u in range(n):
                    for v in range(n):
                        ar, ai, br_, bi = _pair(zg, n, br, v, u)
                        m1 = np.float32(0.5) * np.sqrt((ar + br_) * (ar + br_) + (ai - bi) * (ai - bi))
                        m2 = np.float32(0.5) * np.sqrt((ar - br_) * (ar - br_) + (ai + bi) * (ai + bi))
                        sfs[0, v, u] = m1
                        sfs[1, v, u] = m2
                        smx[0] = max(smx[0], m1)
                        smx[1] = max(smx[1], m2)
                for hf in range(2):
                    for v in range(m):
                        for u in range(m):
                            gmxs[hf, v, u] = max(max(sfs[hf, v, u], sfs[hf, v + m, u]),
                                                 max(sfs[hf, v, u + m], sfs[hf, v + m, u + m]))
            sf = sfs[half]
            gmx = gmxs[half]
            smax = smx[half]
            e = eps * smax + np.float32(1e-30)
            for ch in range(nc):
                py = par[ch, 0]
                px = par[ch, 1]
                qy = (py - ay) & 1
                qx = (px - ax) & 1
                # the lattice's weights and weighted values: zl = w + i w d
                sw = np.float32(0.0)
                sd = np.float32(0.0)
                for i2 in range(m):
                    y = ay + qy + 2 * i2
                    for j2 in range(m):
                        x = ax + qx + 2 * j2
                        kk = 0 <= y < h and 0 <= x < w and known[ch, min(max(y, 0), h - 1), min(max(x, 0), w - 1)]
                        wv = rw[qy + 2 * i2, qx + 2 * j2] if kk else np.float32(0.0)
                        xv = wv * d[ch, y, x] if kk else np.float32(0.0)
                        zl[i2 * m + j2] = wv
                        zl[mm + i2 * m + j2] = xv
                        sw += wv
                        sd += xv
                if sw <= 0.0:
                    for i in range(hb):
                        for j in range(wbk):
                            kk = known[ch, y0 + i, bx + j]
                            out[ch, y0 + i, bx + j] = d[ch, y0 + i, bx + j] if kk else np.float32(0.0)
                    continue
                dm = sd / sw
                for t in range(mm):
                    zl[mm + t] -= dm * zl[t]
                _fft2(zl, m, csl, snl, brl)
                # W_L on the doubled periodic grid (no modulo in the update), R_L on the half spectrum
                for u in range(m):
                    for v in range(m):
                        ar, ai, br_, bi = _pair(zl, m, brl, v, u)
                        wre = np.float32(0.5) * (ar + br_)
                        wim = np.float32(0.5) * (ai - bi)
                        wr[v, u] = wre
                        wi[v, u] = wim
                        wr[v + m, u] = wre
                        wi[v + m, u] = wim
                        wr[v, u + m] = wre
                        wi[v, u + m] = wim
                        wr[v + m, u + m] = wre
                        wi[v + m, u + m] = wim
                        if u < mh:
                            rr[v, u] = np.float32(0.5) * (ai + bi)
                            ri[v, u] = np.float32(0.5) * (br_ - ar)
                w0 = wr[0, 0]
                lim = tau * tau * w0 * w0
                # alias shifts: the peaks of |W| on the full grid (|W(k)| = |W_L(k mod m)|: each peak p_L of
                # |W_L| with its 4 lattice aliases); the guide's maximum over k + p is then that of gmx over
                # (k + p_L) mod m, one value per lattice bin
                npk = 0
                for v in range(m):
                    for u in range(m):
                        if wr[v, u] * wr[v, u] + wi[v, u] * wi[v, u] >= lim:
                            if 4 * (npk + 1) <= MAX_PEAKS:
                                pk_v[npk] = v
                                pk_u[npk] = u
                            npk += 1
                # per lattice bin: the alias of largest selection weight prior(k) ((S(k) + e) / (g + e))^ALPHA
                for v in range(m):
                    for u in range(mh):
                        g4 = smax
                        if 4 * npk <= MAX_PEAKS:
                            g4 = np.float32(0.0)
                            for p in range(npk):
                                g4 = max(g4, gmx[(v + pk_v[p]) & (m - 1), (u + pk_u[p]) & (m - 1)])
                        ig = np.float32(1.0) / (g4 + e)
                        best = np.float32(-1.0)
                        for a4 in range(4):
                            sv = v + m * (a4 >> 1)
                            su = u + m * (a4 & 1)
                            q = (sf[sv, su] + e) * ig
                            pv = prior[sv, su] * (q * q if alpha == 2.0 else q ** alpha)
                            if sv == 0 and su == 0:
                                pv = prior[0, 0]
                            if pv > best:
                                best = pv
                                al_v[v, u] = sv
                                al_u[v, u] = su
                        pb[v, u] = best * best
                # the iterations; the residual update and the next selection in one pass
                best = np.float32(-1.0)
                kv = 0
                ku = 0
                for v in range(m):
                    for u in range(mh):
                        a_ = (rr[v, u] * rr[v, u] + ri[v, u] * ri[v, u]) * pb[v, u]
                        if a_ > best:
                            best = a_
                            kv = v
                            ku = u
                for it in range(iters):
                    cr = gamma * rr[kv, ku] / w0
                    ci = gamma * ri[kv, ku] / w0
                    self_c = kv == 0 and ku == 0
                    if self_c:
                        ci = np.float32(0.0)
                    pc = np.float32(0.0) if self_c else np.float32(1.0)
                    sel_v[it] = al_v[kv, ku]
                    sel_u[it] = al_u[kv, ku]
                    sel_r[it] = cr
                    sel_i[it] = ci
                    kv0 = kv
                    ku0 = ku
                    best = np.float32(-1.0)
                    for v in range(m):
                        av = v - kv0 + m
                        bv = v + kv0
                        for u in range(mh):
                            au = u - ku0 + m
                            bu = u + ku0
                            # c W(j - k) (+ conj(c) W(j + k) for a pair)
                            xr_ = cr * wr[av, au] - ci * wi[av, au] + pc * (cr * wr[bv, bu] + ci * wi[bv, bu])
                            xi_ = cr * wi[av, au] + ci * wr[av, au] + pc * (cr * wi[bv, bu] - ci * wr[bv, bu])
                            r_ = rr[v, u] - xr_
                            i_ = ri[v, u] - xi_
                            rr[v, u] = r_
                            ri[v, u] = i_
                            a_ = (r_ * r_ + i_ * i_) * pb[v, u]
                            if a_ > best:
                                best = a_
                                kv = v
                                ku = u
                # the model on the block's (b + 2) x (b + 2) surround (its phase relative to the lattice's
                # offset q): the lattice band (|k| <= N/4 in both directions) into ib, the components beyond
                # it into ob
                for it in range(iters):
                    sv = sel_v[it]
                    su = sel_u[it]
                    if ((n - sv) & (n - 1)) != sv or ((n - su) & (n - 1)) != su:    # a pair: 2 Re(c e^{i theta})
                        sel_r[it] *= np.float32(2.0)
                        sel_i[it] *= np.float32(2.0)
                    sel_b[it] = min(sv, n - sv) <= q4 and min(su, n - su) <= q4
                for i in range(b + 2):
                    for j in range(b + 2):
                        pi_ = o - 1 + i - qy
                        pj = o - 1 + j - qx
                        ai = dm
                        ao = np.float32(0.0)
                        for it in range(iters):
                            t = (sel_v[it] * pi_ + sel_u[it] * pj) & (n - 1)
                            re = sel_r[it] * cs[t] - sel_i[it] * sn[t]     # Re(c e^{i theta})
                            if sel_b[it]:
                                ai += re
                            else:
                                ao += re
                        yy = y0 - 1 + i
                        xx = bx - 1 + j
                        if 0 <= yy < h and 0 <= xx < w and known[ch, yy, xx]:
                            ai = d[ch, yy, xx] - ao             # the lattice band exact at a known site
                        ib[i, j] = ai
                        ob[i, j] = ao
                for i in range(hb):
                    for j in range(wbk):
                        y = y0 + i
                        x = bx + j
                        if known[ch, y, x]:
                            out[ch, y, x] = d[ch, y, x]
                            continue
                        # the lattice band bilinear from the lattice's sites (rows and columns of parity py, px)
                        ra = i + 1 if (y & 1) == py else i
                        rb = i + 1 if (y & 1) == py else i + 2
                        ca = j + 1 if (x & 1) == px else j
                        cb = j + 1 if (x & 1) == px else j + 2
                        lin = np.float32(0.25) * (ib[ra, ca] + ib[ra, cb] + ib[rb, ca] + ib[rb, cb])
                        out[ch, y, x] = lin + ob[i + 1, j + 1]
    return out
