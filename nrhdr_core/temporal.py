"""Temporal reconstruction: the previous output, aligned by a fast motion estimate, as a prior for the
missing pixels and as extra measurements for the measured and noisy ones, where a per-block consistency
check against the noise model trusts it (docs/TEMPORAL.md).

Anchors: recursive multi-frame frequency selective reconstruction (Jonscher et al., PCS 2016) and
consistency-checked multi-frame reconstruction for a fixed non-regular mask (arXiv 2203.09200); the
recursive, variance-weighted averaging is a motion-compensated recursive (Kalman-type) temporal filter.

Per frame (`TemporalReconstructor.process`):

1. global motion (`global_motion`): the best match within a pixel of still, else phase correlation of
   4 x 4 cell means of log2 values (the frame's measured pixels against the previous output), its peaks
   refined by 2-D matching at full resolution, sub-pixel by parabolic fits;
2. per block (``block`` x ``block``) and candidate motion (none, the global motion rounded and as it is)
   the consistency of the frame's measured pixels with the aligned previous output: z = (m - p)^2 /
   (var_m + var_p + (tol p)^2 + alignment), var_m the measurement's noise (Eq. 4-7 as
   `validity.measurement_variance`), var_p the previous output's variance; the block is trusted when the
   mean of min(z, Z_OUT) stays below ``z_mean`` and few pixels are outliers (z > Z_OUT; a single one in
   a still block restarts that pixel only); most blocks untrusted = a scene cut: the state is reset and
   the frame is reconstructed alone (`reconstruction.reconstruct_frame`, the same bits);
3. cost follows change: with no motion, a still block whose missing and NOISY pixels' past already
   averages ``reuse_frames`` frames is finished in the judgement's pass (`_reuse_row`: measured and NOISY
   pixels averaged with their past, missing ones keep it; undone on a cut);
4. in the other trusted blocks measured pixels are averaged with their aligned past by inverse variance
   (per pixel: an outlier restarts its pixel); the missing pixels are reconstructed from the averaged
   values (runs of block rows as bands, scattered blocks as one mosaic, each in two parts side by side)
   and fused with their past;
5. untrusted blocks (motion the candidates do not explain, occlusion, a block with outliers) are
   reconstructed alone.

Under a budget (option ``budget``: FSE's work a frame in blocks' worth, `TemporalReconstructor._select`)
a restart is the preview's frame alone with placeholders for its missing pixels, and of the still blocks
whose missing pixels are not settled only as many are refined a frame as FSE's work on them fits the
budget (`_fit`: bands and mosaics as `_reconstruct_left` counts them), the fewest reconstructions first,
then the block rows with the most placeholders, then in scan order; the others are reused as they are
(docs/TEMPORAL.md "Budget").

The state (the previous output, its per-pixel variance and frame count) belongs to the instance: one per
stream; `reset` on a seek, flush or caps change.
"""
from __future__ import annotations

import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit, prange

from .scratch import planes
from .states import ATTENUATED, CLIPPED, DARK, NOISY, REASON_MASK, RECONSTRUCTED, VALID
from .validity import clip_lower_row, row_has_clipped_regular

# block decisions
FRESH = 0      # no trusted past: reconstructed alone
REFRESH = 1    # trusted: measured pixels averaged, missing ones reconstructed and fused with their past
REUSE = 2      # trusted and the past of every missing pixel settled: missing pixels keep their past
NO_PRIOR = 3   # trusted measurements but an outlier: measured pixels averaged per pixel, missing ones alone
NO_EVIDENCE = 4  # too few measured pixels to judge: reconstructed alone, not counted for a cut

FAST = {"arcp", "contract", "nsz"}   # numba fastmath flags of the per-pixel passes (no nnan / ninf: NaN and inf
                                    # are tested for)
SNAP = 0.1            # pixels: a global shift this close to an integer is taken as that integer
Z_OUT = 16.0          # z beyond this (4 sigma) is an outlier: its pixel restarts, its block keeps no prior
DEFAULTS = dict(
    block=16,          # decision block (pixels)
    search=32,         # global motion search range (pixels)
    z_mean=2.5,        # a block is consistent when its mean clipped z is below this
    outliers=0.02,     # ... and at most this share (at least 1 pixel) of its measured pixels are outliers
    tol=0.02,          # relative model tolerance of the aligned past (interpolation, slow light changes)
    shift_error=0.25,  # pixels: position error of the global motion (x the squared gradient: a variance)
    cut_share=0.5,     # more untrusted blocks than this share (of blocks with evidence) = a scene cut
    max_frames=16,     # the recursive average of a measured pixel weighs its past at most this many frames
    reuse_frames=4,    # missing pixels whose past averages this many reconstructions are reused as known
    rec_noise=1.0,     # variance of a fresh reconstruction in units of a regular pixel's noise at its level
    rec_tol=0.03,      # ... plus (rec_tol x level)^2: the model error averaging does not remove
    rec_texture=0.5,   # ... plus rec_texture x (half the 3 x 3 range)^2: larger at edges and in texture
    min_evidence=8,    # measured pixels a block needs to be judged
    budget=0,          # FSE's work a frame in a still shot, in blocks' worth (0: no bound; docs/TEMPORAL.md)
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
        for k in ("block", "search", "max_frames", "reuse_frames", "min_evidence", "budget"):
            lo = 0 if k == "budget" else 1
            if not (isinstance(o[k], (int, np.integer)) and not isinstance(o[k], bool) and o[k] >= lo):
                raise ValueError(f"temporal reconstruction: option {k} must be an integer >= {lo}, got {o[k]!r}")
        for k in ("z_mean", "outliers", "tol", "shift_error", "cut_share", "rec_noise", "rec_tol", "rec_texture"):
            if not (isinstance(o[k], (int, float)) and math.isfinite(o[k]) and o[k] >= 0):
                raise ValueError(f"temporal reconstruction: option {k} must be a finite number >= 0, got {o[k]!r}")
        self.method, self.preset, self.use_bounds, self.fusion = method, preset, bool(use_bounds), fusion
        self.options = o
        self._prev = self._var = self._cnt = None
        self._level = self._uns = self._unk = self._hold = self._rank = self._order = None
        self.frames = 0          # frames since the last reset

    def reset(self) -> None:
        """Forget the past: the next frame is reconstructed alone (the state's arrays are kept for it: a
        restart writes every element, without fresh pages to fault in)."""
        self.frames = 0

    # ---- one frame ------------------------------------------------------------------------------------
    def process(self, values: np.ndarray, state: np.ndarray, noise=None) -> dict:
        """Reconstruct the frame in place (float32 values, uint8 states, C-contiguous, as
        `reconstruct_frame`) with the temporal prior; measured pixels of trusted blocks are replaced by
        their recursive average. `noise`: the noise model (gain, read_noise, nd: a CameraProfile; None =
        the default sensor's). Returns the work done: "missing" (pixels filled, as `reconstruct_frame`
        returns), "blocks", the shares "fresh", "refreshed", "reused", "no_prior", "no_evidence" of the
        blocks, "refined" (the share reconstructed by the method this frame), "pending" (the share reused
        before reaching their temporal quality), "chosen" (the share `_select` chose), "motion" (dy, dx):
        the motion most trusted blocks took (the global estimate where none), "cut", "reset" (True when
        the frame was reconstructed alone), "start" (then "preview" or "method") and "reconstructed" (the
        unknown pixels given to the method, a pixel once for each part that holds it) and "work" (the
        method's work on them in unknown pixels' work, `_part_cost`; the budget's unit is `block_worth`)."""
        from . import validity
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
                  "no_prior": 0.0, "no_evidence": 0.0, "motion": (0.0, 0.0), "cut": False, "reset": True,
                  "refined": 0.0, "pending": 0.0, "chosen": 0.0, "start": None, "reconstructed": 0,
                  "work": 0.0}
        if self._prev is not None and self._prev.shape != values.shape:
            self.reset()                     # (`_alone` makes the state's arrays of the new size)
        known, lower, upper, work, pv, pvar, pc, dec, cand, fast = _planes(h, w, nby, nbx)
        g = np.float32(noise.gain)
        floor = np.float32(float(noise.gain) ** 2 * float(noise.read_noise) ** 2 + 1.0 / 12.0)
        nd = np.float32(noise.nd)
        if not self.frames:
            return self._alone(values, state, noise, report, g, floor, nd)
        # 1. global motion
        dy, dx = global_motion(values, state, self._prev, int(o["search"]))
        # 2. per-block consistency; with no motion, settled still blocks (and, under a budget, the unsettled
        # ones not chosen for refinement) are finished in the same pass (their past and output; undone on a cut)
        cy, cx, cmis = _candidates(dy, dx, float(o["shift_error"]))
        sel = planes("temporal.sel", (nby, nbx), lambda: np.empty((nby, nbx), np.uint8))
        chosen = self._select(sel)
        n_kept, n_unknown, n_flagged, n_bad, n = _judge_blocks(
            values, state, self._prev, self._var, self._cnt, cy, cx, bs, dec, cand, fast, work, g, floor,
            nd, np.float32(o["z_mean"]), np.float32(o["outliers"]), np.float32(o["tol"]), np.float32(Z_OUT),
            int(o["min_evidence"]), np.float32(o["reuse_frames"]), cmis, self.use_bounds,
            np.float32(o["max_frames"]), cy.size == 1, sel, self._uns, self._unk)
        if n_flagged or n_bad:
            # pixels filled upstream or non-finite measurements: the general single-frame path judges them
            _undo_fast(values, state, work, fast, bs)
            return self._alone(values, state, noise, report, g, floor, nd)
        counts = np.bincount(dec.ravel(), minlength=5)
        trusted = (dec == REFRESH) | (dec == REUSE) | (dec == NO_PRIOR)
        # the dominant motion: the candidate most trusted blocks took (the global estimate when none did)
        top = int(np.argmax(np.bincount(cand[trusted], minlength=cy.size))) if trusted.any() else -1
        report["motion"] = (float(cy[top]), float(cx[top])) if top >= 0 else (float(dy), float(dx))
        judged = dec.size - counts[NO_EVIDENCE] - n_kept      # blocks with measurements to judge by
        if judged and counts[FRESH] > float(o["cut_share"]) * judged:
            report["cut"] = True
            _undo_fast(values, state, work, fast, bs)
            return self._alone(values, state, noise, report, g, floor, nd)
        if cy.size == 1 and self._order is not None:
            # chosen blocks beyond the budget now: reused as they are, as the judgement reuses the blocks not
            # chosen (the kernel runs on every budgeted still frame, so that the warm-up compiles it)
            late = self._over_budget(dec)
            dec[late != 0] = REUSE
            sel[late != 0] = 0
            n += _reuse_late(values, state, self._prev, self._var, self._cnt, pv, late, fast, bs,
                             self.use_bounds, g, floor, nd, np.float32(o["tol"]), np.float32(Z_OUT),
                             np.float32(o["max_frames"]))
            if late.any():
                counts = np.bincount(dec.ravel(), minlength=5)
        method, preset = self.method, self.preset
        if callable(method):
            method, preset = method(n_unknown / float(h * w)) if n_unknown else ("preview", preset)
        lo_a = lower if self.use_bounds else _EMPTY
        up_a = upper if self.use_bounds else _EMPTY
        if self.use_bounds:        # the clipped-neighbour bounds where blocks are prepared (`work`: the input)
            _clip_lower_rows(work, state, lower, (fast == 0).any(axis=1).astype(np.uint8), bs)
        # 3. the other blocks: measured pixels averaged, settled missing pixels reused, the rest reconstructed
        # C order whatever the count (argwhere's result is Fortran-ordered): one signature, the warm-up's
        blocks = np.argwhere(fast == 0).astype(np.int32, order="C")
        n_todo = n_rec = 0
        n_work = 0.0
        if len(blocks):
            left = np.zeros(len(blocks), np.int64)
            _prepare_blocks(blocks, values, state, self._prev, self._var, self._cnt, cy, cx, bs, dec, cand,
                            known, lo_a, up_a, self.use_bounds, work, pv, pvar, pc, left, g, floor, nd,
                            np.float32(o["tol"]), np.float32(Z_OUT), np.float32(o["max_frames"]), cmis)
            todo = blocks[left > 0]
            n_todo = len(todo)
            if n_todo:
                n_rec, n_work = self._reconstruct_left(todo, left[left > 0], fast, work, known,
                                       lower if self.use_bounds else None, upper if self.use_bounds else None,
                                       state, noise, method, preset)
        # 4. fused with the past, written back, kept as the next frame's past
        n += _finish(values, state, work, pv, pvar, pc, self._prev, self._var, self._cnt, fast, bs, lo_a, up_a,
                    self.use_bounds, g, np.float32(o["rec_noise"]), np.float32(o["rec_tol"]),
                    np.float32(o["reuse_frames"]), floor, np.float32(o["rec_texture"]), nd, np.float32(Z_OUT))
        if self._budgeted(dec.size) and self.frames + 1 >= int(o["reuse_frames"]):
            # a chosen block's reconstruction from measured pixels that average `reuse_frames` frames settles it
            _settle(state, self._cnt, ((sel != 0) & (dec == REFRESH)).astype(np.uint8), bs,
                    np.uint8(min(int(o["reuse_frames"]), 255)))
        # the reconstructions each block's missing pixels average: alone 1, fused with the past one more,
        # reused as they were
        lv = self._level
        lv[(dec == FRESH) | (dec == NO_PRIOR) | (dec == NO_EVIDENCE)] = 1
        np.minimum(lv.astype(np.int32) + (dec == REFRESH), 255, out=lv, casting="unsafe")
        self.frames += 1
        tot = float(dec.size)
        report.update(missing=int(n), reset=False, fresh=counts[FRESH] / tot, refreshed=counts[REFRESH] / tot,
                      reused=counts[REUSE] / tot, no_prior=counts[NO_PRIOR] / tot,
                      no_evidence=counts[NO_EVIDENCE] / tot, refined=n_todo / tot, reconstructed=n_rec,
                      work=n_work,
                      pending=float(np.count_nonzero((self._uns > 0) & (dec == REUSE))) / tot,
                      chosen=chosen / tot)
        return report

    def _budgeted(self, blocks: int) -> bool:
        """True when the budget bounds the work of a frame of `blocks` blocks (0, or at least every block:
        no bound)."""
        b = int(self.options["budget"])
        return 0 < b < blocks

    def _select(self, sel) -> int:
        """sel = 1 at the blocks that may be refined this frame (reconstructed by the method and fused with
        their past when they are still and trusted): without a budget every block; with one, of the blocks
        whose missing pixels are not settled (`_uns`, as the last judgement counted them) in the order the
        fewest reconstructions averaged first (`_level`), then by block row, the rows with the most
        placeholders at the restart first (`_rank`: where the preview stands in for the most missing
        pixels), then in scan order, as many as FSE's work on them fits the budget (`_fit`, their unknown
        pixels as the last judgement counted them: `_unk`). Deterministic: the same frames give the same
        choice; the chosen blocks of a static shot are runs of whole block rows: bands. Returns how many
        blocks with unsettled pixels were chosen."""
        uns = self._uns.ravel()
        self._order = self._est = None
        if not self._budgeted(sel.size):
            sel[...] = 1
            return int(np.count_nonzero(uns))
        bs = int(self.options["block"])
        cap = self._work_cap()
        sel[...] = 0
        cand = np.flatnonzero(uns > 0)
        nbx = sel.shape[1]
        # no more blocks fit than the budget over the least a block can cost (its area in a band, 1 unknown)
        most = min(len(cand), int(cap // _part_cost(bs * bs, 1)) + 1)
        if len(cand):
            key = (self._level.ravel()[cand].astype(np.int64) * sel.size + self._rank[cand // nbx] * nbx
                   + cand % nbx)
            if most < len(cand):
                part = np.argpartition(key, most - 1)[:most]
                cand, key = cand[part], key[part]
            cand = cand[np.argsort(key, kind="stable")]
            cand = cand[:_fit(cand, self._unk, cap, bs, self._prev.shape)]
        sel.ravel()[cand] = 1
        self._order = cand
        self._est = self._unk.ravel()[cand]
        return len(cand)

    def _work_cap(self) -> float:
        """The budget in FSE's work (`_part_cost` units): `budget` blocks' worth (`block_worth`)."""
        return int(self.options["budget"]) * block_worth(int(self.options["block"]))

    def _over_budget(self, dec):
        """After the judgement: where a chosen block now holds more unknown pixels than the selection
        counted (`_unk`, this frame's), the chosen REFRESH blocks that no longer fit the budget (`_fit`, in
        the selection's order), as a (nby, nbx) uint8 mask: they are reused as they are instead, so that
        FSE's work on the chosen blocks never exceeds the budget."""
        late = np.zeros(dec.shape, np.uint8)
        order = self._order
        if not len(order) or not (self._unk.ravel()[order] > self._est).any():
            return late
        k = _fit(order, self._unk, self._work_cap(), int(self.options["block"]), self._prev.shape)
        drop = order[k:]
        late.ravel()[drop[dec.ravel()[drop] == REFRESH]] = 1
        return late

    def _reconstruct_left(self, todo, left, fast, work, known, lower, upper, state, noise, method, preset) -> int:
        """`reconstruction.reconstruct` of the pixels left unknown in the blocks `todo` ((by, bx) rows;
        left: their unknown pixels), in place in `work`, over as little work as it takes (cost follows
        change): each run of consecutive block rows of `todo` as a band (the full width, MARGIN rows of
        context above and below) or as windows of its blocks (each with MARGIN pixels of context) in one
        mosaic, whichever `_part_cost` counts less; the whole frame when that covers no fewer pixels.
        Blocks finished in the judgement (`fast`) enter as known context: their new past. Bands and mosaics
        are cut into PIECES independent parts (`_pieces`) that run side by side. Returns the unknown pixels
        given to the method (a pixel once for each part that holds it) and their work (`_part_cost`:
        the bands' and mosaics' as the choice between them counts it, the whole frame's when that is
        reconstructed)."""
        h, w = work.shape
        bs = int(self.options["block"])
        side = bs + 2 * MARGIN
        nby, nbx = fast.shape
        if h < side or w < side:
            self._fill(fast != 0, work, known, lower, upper)
            self._reconstruct_rows(work, known, lower, upper, state, noise, method, preset, 0, h)
            unknown = h * w - int(np.count_nonzero(known))
            return unknown, _part_cost(h * w, unknown)
        # the unknown pixels a window reaches: its block's and its neighbours' within MARGIN (the only
        # unknown pixels are those of `todo`): adjacent windows of a mosaic reconstruct each other's again
        r = -(-MARGIN // bs)
        unk = np.zeros((nby + 2 * r, nbx + 2 * r), np.int64)
        unk[todo[:, 0] + r, todo[:, 1] + r] = left
        reach = sum(unk[r + dy:nby + r + dy, r + dx:nbx + r + dx] for dy in range(-r, r + 1) for dx in range(-r, r + 1))
        rows = np.unique(todo[:, 0])
        bands, rest = [], []
        cost = 0.0
        for run in np.split(rows, np.flatnonzero(np.diff(rows) > 1) + 1):
            inside = (todo[:, 0] >= run[0]) & (todo[:, 0] <= run[-1])
            y0, y1 = max(int(run[0]) * bs - MARGIN, 0), min(int(run[-1]) * bs + bs + MARGIN, h)
            band = _part_cost((y1 - y0) * w, int(left[inside].sum()))
            mosaic = _part_cost(int(inside.sum()) * side * side,
                                int(reach[todo[inside, 0], todo[inside, 1]].sum()))
            cost += min(band, mosaic)
            if band < mosaic:
                bands.append((y0, y1))
            else:
                rest.append(todo[inside])
        rest = np.concatenate(rest) if rest else todo[:0]
        if sum((y1 - y0) * w for y0, y1 in bands) + len(rest) * side * side >= h * w:
            self._fill(fast != 0, work, known, lower, upper)
            self._reconstruct_rows(work, known, lower, upper, state, noise, method, preset, 0, h)
            unknown = h * w - int(np.count_nonzero(known))
            return unknown, _part_cost(h * w, unknown)
        near = np.zeros((nby, nbx), np.bool_)            # the finished blocks the bands and windows reach into
        for y0, y1 in bands:
            near[y0 // bs:(y1 - 1) // bs + 1, :] = True
        ys = np.clip(rest[:, 0] * bs - MARGIN, 0, h - side)
        xs = np.clip(rest[:, 1] * bs - MARGIN, 0, w - side)
        for y0, x0 in zip(ys, xs):
            near[y0 // bs:(y0 + side - 1) // bs + 1, x0 // bs:(x0 + side - 1) // bs + 1] = True
        self._fill(near & (fast != 0), work, known, lower, upper)
        return (self._pieces(bands, rest, ys, xs, side, work, known, lower, upper, state, noise, method, preset),
                cost)

    def _pieces(self, bands, rest, ys, xs, side, work, known, lower, upper, state, noise, method, preset) -> int:
        """The bands ((y0, y1) rows of `work`) and the mosaic of the blocks `rest` (context windows side x
        side at (ys, xs)) reconstructed in PIECES parts each: a band wider than PIECES x 4 blocks as column
        ranges split at block boundaries (each with MARGIN columns of context across the cut), the mosaic
        as PIECES mosaics of consecutive blocks. Every part reads its input before any part writes, so the
        output does not depend on their order or the threads (the parts are fixed by the counts); they run
        on `_POOL` (FSE runs a band of a few block rows on one thread). Returns the unknown pixels of the
        parts."""
        h, w = work.shape
        bs = int(self.options["block"])
        nbx = (w + bs - 1) // bs
        parts = []                  # (rows, write columns x0..x1 of the band) or (mosaic blocks, ys, xs)
        for y0, y1 in bands:
            cuts = [0, w]
            if nbx >= PIECES * 4:
                cuts = [0] + [(nbx * i // PIECES) * bs for i in range(1, PIECES)] + [w]
            parts += [("band", y0, y1, x0, x1, max(x0 - MARGIN, 0) if x0 else 0, min(x1 + MARGIN, w))
                      for x0, x1 in zip(cuts[:-1], cuts[1:])]
        if len(rest):
            for i in np.array_split(np.arange(len(rest)), min(PIECES, len(rest))):
                parts.append(("mosaic", rest[i], ys[i], xs[i]))

        def take(a, part):
            if a is None:
                return None
            if part[0] == "band":
                _, y0, y1, _, _, c0, c1 = part
                return np.ascontiguousarray(a[y0:y1, c0:c1])
            _, blocks, py, px = part
            rr = (py[:, None] + np.arange(side)[None, :])[:, :, None]
            cc = (px[:, None] + np.arange(side)[None, :])[:, None, :]
            return np.ascontiguousarray(a[rr, cc].reshape(len(blocks) * side, side))

        inputs = [tuple(take(a, part) for a in (work, known, state, lower, upper)) for part in parts]
        unknown = sum(k.size - int(np.count_nonzero(k)) for _, k, _, _, _ in inputs)
        outs = list(_run_parts(lambda args: self._reconstruct_part(*args, noise, method, preset), inputs))
        for part, sub in zip(parts, outs):
            if part[0] == "band":
                _, y0, y1, x0, x1, c0, _ = part
                work[y0:y1, x0:x1] = sub[:, x0 - c0:x1 - c0]
                continue
            _, blocks, py, px = part
            sub = sub.reshape(len(blocks), side, side)
            for i, (by, bx) in enumerate(blocks):
                y0, x0 = by * bs, bx * bs
                y1, x1 = min(y0 + bs, h), min(x0 + bs, w)
                oy, ox = y0 - py[i], x0 - px[i]
                work[y0:y1, x0:x1] = sub[i, oy:oy + y1 - y0, ox:ox + x1 - x0]
        return unknown

    def _reconstruct_part(self, sub, k, st, lo, up, noise, method, preset):
        """`reconstruction.reconstruct` of one part of `_pieces` (its own arrays), in place; returns it."""
        from . import reconstruction
        noisy = ((st & (REASON_MASK | RECONSTRUCTED)) == NOISY) & ~k
        noisy = noisy if noisy.any() else None
        return reconstruction.reconstruct(sub, k, method=method, preset=preset, lower=lo, upper=up, out=sub,
                                          noisy=noisy, noise=noise if noisy is not None else None,
                                          fusion=self.fusion)

    def _fill(self, blocks, work, known, lower, upper) -> None:
        """The blocks `blocks` (a (by, bx) mask) finished in the judgement as known context (`_fill_fast`)."""
        _fill_fast(np.argwhere(blocks).astype(np.int32, order="C"), self._prev, int(self.options["block"]), work, known,
                   lower if lower is not None else _EMPTY, upper if upper is not None else _EMPTY,
                   lower is not None)

    def _reconstruct_rows(self, work, known, lower, upper, state, noise, method, preset, y0, y1) -> None:
        """`reconstruction.reconstruct` of rows y0..y1-1 of `work`, in place."""
        lo = None if lower is None else lower[y0:y1]
        up = None if upper is None else upper[y0:y1]
        self._reconstruct_part(work[y0:y1], known[y0:y1], state[y0:y1], lo, up, noise, method, preset)

    def _alone(self, values, state, noise, report, g, floor, nd) -> dict:
        """The frame reconstructed alone (`reconstruct_frame`, the same bits); the state restarts from it.
        Under a budget (`_budgeted`) by the preview method: its missing pixels are placeholders (no
        variance, no frame averaged) that the budgeted refinement replaces block by block."""
        from . import reconstruction
        o = self.options
        bs = int(o["block"])
        h, w = values.shape
        nby, nbx = (h + bs - 1) // bs, (w + bs - 1) // bs
        preview = self._budgeted(nby * nbx)
        report["missing"] = int(reconstruction.reconstruct_frame(
            values, state, method="preview" if preview else self.method, preset=self.preset,
            use_bounds=self.use_bounds, noise=noise, fusion=self.fusion))
        if self._prev is None or self._prev.shape != values.shape or self._uns.shape != (nby, nbx):
            self._prev = np.empty_like(values)
            self._var = np.empty_like(values)
            self._cnt = np.empty(values.shape, np.uint8)
            self._level = np.empty((nby, nbx), np.uint8)
            self._uns = np.empty((nby, nbx), np.int32)
            self._unk = np.empty((nby, nbx), np.int32)
            self._hold = np.empty(nby, np.int64)
        _restart(values, state, self._prev, self._var, self._cnt, g, floor, nd, np.float32(o["rec_noise"]),
                 np.float32(o["rec_tol"]), np.float32(o["rec_texture"]), preview, bs,
                 np.float32(o["reuse_frames"]), self._uns, self._unk, self._hold)
        self._level[...] = 0 if preview else 1
        # block rows by their placeholders, most first (ties in scan order): the order `_select` refines in
        self._rank = np.empty(nby, np.int64)
        self._rank[np.argsort(-self._hold, kind="stable")] = np.arange(nby)
        self.frames = 1
        tot = float(nby * nbx)
        has = float(np.count_nonzero(self._uns)) / tot
        report.update(refined=0.0 if preview else has, pending=has if preview else 0.0, chosen=0.0,
                      start="preview" if preview else "method")
        return report


_EMPTY = np.full((1, 1), np.nan, np.float32)
MARGIN = 16          # pixels of context around a block reconstructed in a mosaic (FSE's support: 16 or 32)
AREA_COST = 0.12     # FSE's work per pixel of a part (its domain, plan and bounds) in unknown pixels' work
PIECES = 2           # parts a band or mosaic is reconstructed in, side by side (`_pieces`; the 2-core target)
_POOL = []           # the threads the parts run on (one executor, made on first use)
_POOL_LOCK = threading.Lock()


def _forget_pool() -> None:
    """In a forked child: the parent's pool threads do not exist there; the first use makes a new pool."""
    global _POOL_LOCK
    _POOL.clear()
    _POOL_LOCK = threading.Lock()


os.register_at_fork(after_in_child=_forget_pool)


def block_worth(block: int = 16) -> float:
    """The unit of the temporal budget, in `_part_cost` units (unknown pixels' work): the work of a block
    every pixel of which is unknown, in a band (its area with MARGIN rows of context above and below)."""
    return _part_cost(block * (block + 2 * MARGIN), block * block)


def _part_cost(area, unknown) -> float:
    """The work of reconstructing a part (band or mosaic) of `area` pixels holding `unknown` unknown pixels,
    in unknown pixels' work: FSE's passes over the part (AREA_COST a pixel) and its windows, as many as the
    unknown pixels it holds (a mosaic's windows hold their neighbours' too)."""
    return AREA_COST * area + unknown


def _fit(order, unk, cap, bs, shape) -> int:
    """How many of the blocks `order` (flat indices, in the order they are chosen) fit a budget of `cap` in
    FSE's work (`_part_cost`), reconstructed as `TemporalReconstructor._reconstruct_left` does: each run of
    consecutive block rows as a band or a mosaic, whichever costs less (unk: the blocks' unknown pixels).
    Whole runs of one block row are tried at once (vectorised): the work of the first k blocks of a run
    grows with k. At least one block (a budget smaller than a block still refines the shot)."""
    h, w = shape
    nby, nbx = unk.shape
    side = bs + 2 * MARGIN
    r = -(-MARGIN // bs)
    rows = order // nbx
    cols = order % nbx
    u_all = unk.ravel()[order].astype(np.float64)
    su = np.zeros((nby + 2 * r, nbx + 2 * r))        # the chosen blocks' unknown pixels (reach of a window)
    sn = np.zeros((nby + 2 * r, nbx + 2 * r))        # 1 at the chosen blocks
    band_u = np.zeros(nby)                            # per block row: the chosen blocks' unknown pixels
    mos = np.zeros(nby)                               # ... their mosaic's work (neighbours' reach included)
    has = np.zeros(nby, np.bool_)
    starts = np.r_[0, np.flatnonzero(np.diff(rows) != 0) + 1, len(order)]

    def runs_cost(mask):
        """The work of the runs of block rows `mask` marks: per run min(band, mosaic)."""
        if not mask.any():
            return 0.0
        idx = np.flatnonzero(mask)
        cuts = np.flatnonzero(np.diff(idx) > 1) + 1
        total = 0.0
        for run in np.split(idx, cuts):
            y0, y1 = max(int(run[0]) * bs - MARGIN, 0), min(int(run[-1]) * bs + bs + MARGIN, h)
            total += min(_part_cost((y1 - y0) * w, band_u[run].sum()), mos[run].sum())
        return total

    taken = 0
    for a, b in zip(starts[:-1], starts[1:]):
        row = int(rows[a])
        c = cols[a:b]
        u = u_all[a:b]
        # each block's mosaic work: its window's area and unknown pixels, and the reach between it and the
        # chosen blocks around it (both ways); neighbours earlier in this run of the row counted too
        win_u = sum(su[row + r + dy, c + r + dx] for dy in range(-r, r + 1) for dx in range(-r, r + 1))
        win_n = sum(sn[row + r + dy, c + r + dx] for dy in range(-r, r + 1) for dx in range(-r, r + 1))
        dm = _part_cost(side * side, u) + win_u + win_n * u
        if len(c) > 1:
            # earlier blocks of this run within r columns of each later one (the runs are in column order)
            for k in range(1, r + 1):
                near = (c[k:] - c[:-k]) <= r
                dm[k:] += near * (u[:-k] + u[k:])
        was = has[row]
        has[row] = True
        lo = hi = row
        while lo > 0 and has[lo - 1]:
            lo -= 1
        while hi < nby - 1 and has[hi + 1]:
            hi += 1
        inrun = np.zeros(nby, np.bool_)
        inrun[lo:hi + 1] = True
        other = runs_cost(has & ~inrun)
        y0, y1 = max(lo * bs - MARGIN, 0), min(hi * bs + bs + MARGIN, h)
        band = _part_cost((y1 - y0) * w, band_u[lo:hi + 1].sum() + np.cumsum(u))
        mosaic = mos[lo:hi + 1].sum() + np.cumsum(dm)
        k = int(np.searchsorted(other + np.minimum(band, mosaic), cap, side="right"))
        if k == 0 and taken == 0:
            k = 1
        if k < len(c):
            has[row] = was or k > 0
            return taken + k
        band_u[row] += u.sum()
        mos[row] += dm.sum()
        su[row + r, c + r] = u
        sn[row + r, c + r] = 1
        taken += len(c)
    return taken


def _run_parts(fn, items):
    """fn over items, side by side on `_POOL` (the calling thread alone for one item); results in order."""
    if len(items) <= 1:
        return [fn(x) for x in items]
    with _POOL_LOCK:
        if not _POOL:
            _POOL.append(ThreadPoolExecutor(max_workers=PIECES, thread_name_prefix="nrhdr-temporal"))
    return list(_POOL[0].map(fn, items))


def _planes(h, w, nby, nbx):
    """The calling thread's working planes: known, lower, upper, work, aligned past, its variance and its
    count, block decisions, candidates and the blocks finished in the judgement."""
    return planes("temporal.work", (h, w, nby, nbx), lambda: (
        np.empty((h, w), np.bool_), np.empty((h, w), np.float32), np.empty((h, w), np.float32),
        np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w), np.float32),
        np.empty((h, w), np.uint8), np.empty((nby, nbx), np.uint8), np.empty((nby, nbx), np.uint8),
        np.empty((nby, nbx), np.uint8)))


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


@njit(cache=True, nogil=True, inline="always")
def _tex_var(img, y, x, h, w, rec_tex):
    """rec_tex x (half the range of the 3 x 3 around (y, x))^2: a reconstruction's uncertainty grows with
    the local contrast (edges, texture)."""
    lo = img[y, x]
    hi = lo
    for yy in range(max(y - 1, 0), min(y + 2, h)):
        for xx in range(max(x - 1, 0), min(x + 2, w)):
            a = img[yy, xx]
            lo = a if a < lo else lo
            hi = a if a > hi else hi
    r = np.float32(0.5) * (hi - lo)
    return rec_tex * r * r


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _restart(values, state, prev, var, cnt, g, floor, nd, rec_noise, rec_tol, rec_tex, placeholder, bs,
             reuse_frames, uns, unk, held):
    """The past after a frame reconstructed alone: its output, measured pixels with their noise variance,
    the others with a fresh reconstruction's (+ `_tex_var`), each the average of 1 frame; with
    `placeholder` (a preview start) the missing pixels that are not NOISY as no frame averaged (variance
    inf, count 0): the first reconstruction of their block replaces them. uns[by, bx] = the block's
    pixels not VALID whose past averages fewer than `reuse_frames` frames (unsettled, as `_still_rows`
    counts them), unk[by, bx] = its pixels not VALID; held[by] = the placeholders of block row by. One
    pass per block row, branch-free over whole rows (it vectorises)."""
    h, w = values.shape
    nby, nbx = uns.shape
    inf = np.float32(np.inf)
    half = np.float32(0.5)
    ndg = nd * g
    ndf = nd * nd * floor
    for by in prange(nby):
        lo3 = np.empty(w, np.float32)       # the 3 x 1 column's min and max around each pixel of the row
        hi3 = np.empty(w, np.float32)
        tx = np.empty(w, np.float32)
        ul = np.zeros(w, np.int32)          # unsettled pixels per column of the block row
        ua = np.zeros(w, np.int32)          # pixels not VALID per column of the block row
        nh = 0                              # placeholders in the block row
        for y in range(by * bs, min(by * bs + bs, h)):
            ra = values[max(y - 1, 0)]
            rb = values[y]
            rc = values[min(y + 1, h - 1)]
            for x in range(w):
                a = ra[x]
                b = rb[x]
                c = rc[x]
                lo = b
                lo = a if a < lo else lo
                lo = c if c < lo else lo
                hi = b
                hi = a if a > hi else hi
                hi = c if c > hi else hi
                lo3[x] = lo
                hi3[x] = hi
            for x in range(1, w - 1):        # the 3 x 3 range, then the texture term (`_tex_var`)
                lo = lo3[x - 1]
                lo = lo3[x] if lo3[x] < lo else lo
                lo = lo3[x + 1] if lo3[x + 1] < lo else lo
                hi = hi3[x - 1]
                hi = hi3[x] if hi3[x] > hi else hi
                hi = hi3[x + 1] if hi3[x + 1] > hi else hi
                rr = half * (hi - lo)
                tx[x] = rec_tex * rr * rr
            for x in (0, w - 1):
                lo = lo3[x]
                hi = hi3[x]
                for xx in range(max(x - 1, 0), min(x + 2, w)):
                    lo = lo3[xx] if lo3[xx] < lo else lo
                    hi = hi3[xx] if hi3[xx] > hi else hi
                rr = half * (hi - lo)
                tx[x] = rec_tex * rr * rr
            sr = state[y]
            pr = prev[y]
            qr = var[y]
            cr = cnt[y]
            for x in range(w):
                v = rb[x]
                st = sr[x]
                r = st & REASON_MASK
                m = v if v > 0 else np.float32(0.0)
                vm = (ndg * m + ndf) if (st & ATTENUATED) != 0 else (g * m + floor)
                vr = rec_noise * (g * m + floor) + (rec_tol * m) * (rec_tol * m) + tx[x]
                ph = placeholder & (r != VALID) & (r != NOISY)
                pr[x] = v
                qr[x] = vm if r == VALID else (inf if ph else vr)
                c = np.uint8(0) if ph else np.uint8(1)
                cr[x] = c
                ul[x] += np.int32((r != VALID) & (np.float32(c) < reuse_frames))
                ua[x] += np.int32(r != VALID)
                nh += np.int64(ph)
        for bx in range(nbx):
            t = 0
            a = 0
            for x in range(bx * bs, min(bx * bs + bs, w)):
                t += ul[x]
                a += ua[x]
            uns[by, bx] = t
            unk[by, bx] = a
        held[by] = nh


@njit(cache=True, nogil=True, parallel=True)
def _settle(state, cnt, blocks, bs, n):
    """The pixels not VALID of the blocks `blocks` marks average at least n frames (settled)."""
    h, w = state.shape
    nby, nbx = blocks.shape
    for by in prange(nby):
        for bx in range(nbx):
            if blocks[by, bx] == 0:
                continue
            for y in range(by * bs, min(by * bs + bs, h)):
                for x in range(bx * bs, min(bx * bs + bs, w)):
                    c = cnt[y, x]
                    if (state[y, x] & REASON_MASK) != VALID and c < n:
                        cnt[y, x] = n


@njit(cache=True, nogil=True, inline="always")
def _count_at(cnt, y, x, sy, sx, h, w):
    """Frames averaged in the past at the pixel nearest to (y - sy, x - sx) (0 outside the frame)."""
    yy = int(math.floor(np.float32(y) - sy + np.float32(0.5)))
    xx = int(math.floor(np.float32(x) - sx + np.float32(0.5)))
    if yy < 0 or xx < 0 or yy >= h or xx >= w:
        return 0
    return np.int32(cnt[yy, xx])


# ---- global motion: phase correlation and matching of log2 values -------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _log2f(bits):
    """log2 of a float32 from its bits (exponent + linear mantissa; within 0.09 stops), values below 1 as 1."""
    one = np.int32(0x3F800000)
    b = bits if bits > one else one
    return np.float32(b - one) * np.float32(1.0 / 8388608.0)


CELL = 4              # pixels: the phase correlation works on CELL x CELL means of log2 values
PEAKS = 3             # its strongest peaks are refined (and no motion), the best match is the estimate


@njit(cache=True, nogil=True, parallel=True)
def _cell_means(values, state, prev, cell, cur, past):
    """cur = mean log2 of the measured (VALID) pixels of each cell (NaN where none), past = mean log2 of
    all the previous output's pixels of the cell."""
    hc, wc = cur.shape
    vi = values.view(np.int32)
    pi = prev.view(np.int32)
    for cy in prange(hc):
        for cx in range(wc):
            sc = np.float32(0.0)
            nc = np.float32(0.0)
            sp = np.float32(0.0)
            for y in range(cy * cell, cy * cell + cell):
                for x in range(cx * cell, cx * cell + cell):
                    kf = np.float32(1.0) if (state[y, x] & REASON_MASK) == VALID else np.float32(0.0)
                    sc += kf * _log2f(vi[y, x])
                    nc += kf
                    sp += _log2f(pi[y, x])
            cur[cy, cx] = sc / nc if nc > 0 else np.float32(np.nan)
            past[cy, cx] = sp / np.float32(cell * cell)


def _peak_fit(r, i, j):
    """Sub-cell offset of the peak r[i, j] along each axis (parabola through the neighbours, cyclic)."""
    def fit(a, b, c):
        den = a - 2.0 * b + c
        return float(min(max(0.5 * (a - c) / den, -0.5), 0.5)) if den < 0 else 0.0
    h, w = r.shape
    return (fit(r[(i - 1) % h, j], r[i, j], r[(i + 1) % h, j]),
            fit(r[i, (j - 1) % w], r[i, j], r[i, (j + 1) % w]))


def global_motion(values, state, prev, search: int = 32):
    """(dy, dx) of the frame against the previous output `prev`: content at (y, x) of the frame was at
    (y - dy, x - dx). Phase correlation (Kuglin & Hines 1975) of CELL x CELL means of log2 values (the
    frame's measured pixels, the past's all pixels; Hann window) within `search` pixels: its PEAKS strongest
    peaks and no motion, each refined at full resolution (`refine_motion`); the best match wins. When the
    best match within a pixel of no motion is inside that pixel, that is the estimate (no search)."""
    h, w = values.shape
    hc, wc = h // CELL, w // CELL
    still = refine_motion(values, state, prev, 0.0, 0.0, with_cost=True, rad=1)
    if (abs(still[0]) < 1 and abs(still[1]) < 1) or hc < 4 or wc < 4:
        return still[0], still[1]          # less than a pixel from still: no search needed
    cur, past = planes("temporal.cells", (hc, wc), lambda: (np.empty((hc, wc), np.float32),
                                                           np.empty((hc, wc), np.float32)))
    _cell_means(values, state, prev, CELL, cur, past)
    ok = np.isfinite(cur)
    if ok.sum() < 16:
        return still[0], still[1]
    a = np.where(ok, cur, np.float32(cur[ok].mean())) - np.float32(cur[ok].mean())
    b = past - past.mean()
    win = np.outer(np.hanning(hc), np.hanning(wc)).astype(np.float32)
    fa = np.fft.rfft2(a * win)
    fb = np.fft.rfft2(b * win)
    x = fa * np.conj(fb)
    x /= np.maximum(np.abs(x), 1e-12)
    r = np.fft.irfft2(x, s=(hc, wc))
    lim_y = min(int(search) // CELL + 1, hc // 2)
    lim_x = min(int(search) // CELL + 1, wc // 2)
    sy = np.r_[0:lim_y + 1, hc - lim_y:hc]
    sx = np.r_[0:lim_x + 1, wc - lim_x:wc]
    sub = r[np.ix_(sy, sx)].copy()
    best = None
    for _ in range(PEAKS):             # the strongest peaks (and no motion), each refined; the best match wins
        ii, jj = np.unravel_index(int(np.argmax(sub)), sub.shape)
        i, j = int(sy[ii]), int(sx[jj])
        fy, fx = _peak_fit(r, i, j)
        sub[max(ii - 1, 0):ii + 2, max(jj - 1, 0):jj + 2] = -np.inf
        dy = ((i + hc // 2) % hc - hc // 2 + fy) * CELL
        dx = ((j + wc // 2) % wc - wc // 2 + fx) * CELL
        cand = refine_motion(values, state, prev, dy, dx, with_cost=True)
        best = cand if best is None or cand[2] < best[2] else best
    best = still if still[2] < best[2] else best
    return best[0], best[1]


REFINE_RADIUS = CELL // 2 + 1   # pixels: the refinement searches this far around the cells' estimate ...
REFINE_SAMPLES = 10000          # ... on about this many pixels (every n-th row and column)


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


def refine_motion(values, state, prev, dy: float, dx: float, with_cost: bool = False, rad: int = REFINE_RADIUS):
    """(dy, dx) refined by 2-D matching of the frame's measured pixels against the past's log2 values
    within `rad` of the rounded estimate (`_match_costs`, about REFINE_SAMPLES pixels): the best
    whole-pixel shift and a parabolic sub-pixel fit along each axis, snapped to an integer within SNAP;
    `with_cost`: and the match cost of that whole-pixel shift."""
    n = 2 * rad + 1
    cost = planes("temporal.match", n, lambda: np.empty((n, n), np.float64))
    oy, ox = int(round(dy)), int(round(dx))
    step = max(2, int(math.sqrt(values.size / REFINE_SAMPLES)))
    _match_costs(values, state, prev, oy, ox, rad, step, cost)
    if not np.isfinite(cost).any():
        return (dy, dx, np.inf) if with_cost else (dy, dx)
    i, j = np.unravel_index(int(np.argmin(cost)), cost.shape)

    def fit(a, b, c):
        den = a - 2.0 * b + c
        return float(min(max(0.5 * (a - c) / den, -0.5), 0.5)) if den > 0 and np.isfinite(a + c) else 0.0

    fy = fit(cost[i - 1, j], cost[i, j], cost[i + 1, j]) if 0 < i < n - 1 else 0.0
    fx = fit(cost[i, j - 1], cost[i, j], cost[i, j + 1]) if 0 < j < n - 1 else 0.0
    out = (_snap(oy + i - rad + fy), _snap(ox + j - rad + fx))
    return out + (float(cost[i, j]),) if with_cost else out


def _snap(d: float) -> float:
    """A shift within SNAP of an integer is that integer (no interpolation blur for a still camera)."""
    r = round(d)
    return float(r) if abs(d - r) < SNAP else float(d)


def _candidates(dy: float, dx: float, err: float):
    """The motions a block may take, in the order of preference (float32 arrays cy, cx): none, the global
    motion rounded to whole pixels (no interpolation), the global motion; and the squared position error
    each is given (cmis): 0 for none (a still block is exact), err^2 + its distance to the global motion
    squared for the others."""
    out = [(0.0, 0.0)]
    for c in ((float(round(dy)), float(round(dx))), (dy, dx)):
        if c not in out:
            out.append(c)
    a = np.array(out, np.float32)
    mis = np.array([0.0] + [err * err + (y - dy) ** 2 + (x - dx) ** 2 for y, x in out[1:]], np.float32)
    return np.ascontiguousarray(a[:, 0]), np.ascontiguousarray(a[:, 1]), mis


# ---- the aligned past ----------------------------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _aligned(prev, var, y, x, sy, sx, h, w, mis2):
    """(value, variance, alignment variance) of the past at (y - sy, x - sx), bilinear; variance inf
    outside the frame. The alignment variance: mis2 (the candidate's position error squared, pixels^2) x
    the squared local gradient, plus at a sub-pixel position the interpolation's: (local range / 2)^2 x
    4 f (1 - f)."""
    fy = np.float32(y) - sy
    fx = np.float32(x) - sx
    if fy < 0 or fx < 0 or fy > h - 1 or fx > w - 1:
        return np.float32(0.0), np.float32(np.inf), np.float32(0.0)
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
        return a, var[y0, x0], extra
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
    return p, vp, half * half * s + extra


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _judge_blocks(values, state, prev, var, cnt, cy, cx, bs, dec, cand, fast, work, g, floor, nd, z_mean,
                  out_share, tol, z_out, min_ev, reuse_frames, cmis, use_bounds, max_frames, allow_fast, sel, uns,
                  unk):
    """Per block: the candidate motion (`_candidates`: (cy[c], cx[c])) that explains the measured pixels
    (VALID and NOISY) best, and the decision (FRESH, REFRESH, REUSE, NO_PRIOR, NO_EVIDENCE). With
    `allow_fast` (no motion: the only candidate is none; every read is of the block's own pixels) a REUSE
    block without pixels filled upstream or non-finite measurements is finished right here, in cache
    (`_reuse_row` once the block row is judged: its past and its output), fast = 1; `work` = the input
    values of every row (for `_undo_fast` and the bounds of the blocks prepared after);
    the general path skips it. A still trusted block whose missing pixels are not settled is reused as it
    is unless sel[by, bx] chose it for refinement; uns[by, bx] = its unsettled pixels (`_still_rows`),
    unk[by, bx] = its pixels not VALID.
    Returns the blocks trusted on their bounds
    alone, the pixels not VALID, those of them already RECONSTRUCTED, the VALID pixels that are not
    finite, and the pixels not VALID written."""
    h, w = values.shape
    nby, nbx = dec.shape
    nc = cy.shape[0]
    n_kept = 0
    n_unknown = 0
    n_flagged = 0
    n_bad = 0
    n_written = 0
    for by in prange(nby):
        zl = np.empty(w, np.float32)        # the still fit's per-column sums over the block row (`_still_rows`)
        il = np.empty((6, w), np.int32)
        la = np.empty(w, np.float32)        # the reused blocks' rows (`_reuse_row`)
        lv = np.empty(w, np.float32)
        lc = np.empty(w, np.uint8)
        fm = np.zeros(w, np.uint8)
        c_written = 0
        _still_rows(values, state, prev, var, cnt, by * bs, min(by * bs + bs, h), g, floor, nd, tol, z_out,
                    reuse_frames, zl, il)
        for bx in range(nbx):
            y0 = by * bs
            x0 = bx * bs
            y1 = min(y0 + bs, h)
            x1 = min(x0 + bs, w)
            fast[by, bx] = 0
            best_m = np.float32(np.inf)
            best_r = np.float32(np.inf)
            best_o = 0
            best_n = 0
            best_c = 0
            unsettled = 0
            blk_bad = 0
            for c in range(nc):
                sy = cy[c]
                sx = cx[c]
                zr = np.float32(0.0)
                zs = np.float32(0.0)
                n = 0
                no = 0
                if c == 0:
                    # still: the past at the same pixel, branch-free (the mask is random)
                    zr, n, no, nu, nf, nb, unsettled = _lane_sums(zl, il, x0, x1)
                    zs = zr
                    n_unknown += nu
                    unk[by, bx] = nu
                    n_flagged += nf
                    blk_bad = nf + nb
                    n_bad += nb
                for y in range(y0, y1 if c > 0 else y0):
                    for x in range(x0, x1):
                        st = state[y, x]
                        r = st & REASON_MASK
                        if r != VALID and r != NOISY:
                            continue
                        p, vp, va = _aligned(prev, var, y, x, sy, sx, h, w, cmis[c])
                        if not vp < np.inf:
                            continue
                        vm = _meas_var(p, (st & ATTENUATED) != 0 or r == NOISY, g, floor, nd)
                        d = values[y, x] - p
                        t = tol * p
                        base = vm + vp + t * t
                        zr += min(d * d / base, z_out)         # the fit, for the choice of the candidate
                        z = d * d / (base + va)                # with the alignment's uncertainty, for trust
                        zs += min(z, z_out)
                        n += 1
                        no += 1 if d * d > z_out * (base + va) else 0
                mr = zr / n if n > 0 else np.float32(np.inf)
                m = zs / n if n > 0 else np.float32(np.inf)
                if c == 0 or mr < best_r * np.float32(0.9):     # a later candidate must fit clearly better
                    best_r = mr
                    best_m = m
                    best_o = no
                    best_n = n
                    best_c = c
                if mr < np.float32(0.6) * z_mean and no == 0:
                    break          # explained well: the later candidates are not tried
            cand[by, bx] = best_c
            uns[by, bx] = unsettled
            kept = False
            if best_n < min_ev:
                # too few measurements (a saturated or black area): still, when the past keeps every
                # bound of the block (clipped pixels at or above, dark ones at or below), it is trusted
                if _bounds_kept(values, state, prev, y0, y1, x0, x1, tol):
                    cand[by, bx] = 0
                    best_c = 0
                    kept = True
                    n_kept += 1
                else:
                    dec[by, bx] = NO_EVIDENCE
                    continue
            if (not kept) and (best_m >= z_mean or best_o > max(np.float32(1.0), out_share * best_n)):
                dec[by, bx] = FRESH
            elif (not kept) and best_o > 0 and not ((best_c == 0) & (best_o == 1)):
                # an outlier: the missing pixels keep no prior (a single one in a still block is the
                # noise's: that pixel alone restarts from its measurement)
                dec[by, bx] = NO_PRIOR
            else:
                # reusable when the past of every missing pixel averages `reuse_frames` reconstructions (or
                # noisy measurements)
                # (only where nothing moved: a past moved by a whole-pixel estimate of a motion that is
                # not would be copied with its position error, frame after frame)
                # (or not chosen for refinement this frame: `sel`)
                reuse = (best_c == 0) & ((unsettled == 0) | (sel[by, bx] == 0))
                dec[by, bx] = REUSE if reuse else REFRESH
                if reuse & allow_fast & (blk_bad == 0):
                    fast[by, bx] = 1
                    fm[x0:x1] = 1
        if fm.any():
            for y in range(by * bs, min(by * bs + bs, h)):
                c_written += _reuse_row(values, state, prev, var, cnt, work, y, fm, use_bounds, g, floor,
                                        nd, tol, z_out, max_frames, la, lv, lc)
        else:
            for y in range(by * bs, min(by * bs + bs, h)):
                work[y, :] = values[y, :]
        n_written += c_written
    return n_kept, n_unknown, n_flagged, n_bad, n_written


@njit(cache=True, nogil=True, error_model="numpy", fastmath=FAST)
def _still_rows(values, state, prev, var, cnt, y0, y1, g, floor, nd, tol, z_out, reuse_frames, zl, il):
    """Per column of rows y0..y1-1, the still candidate's terms of `_judge_blocks` (the past at the same
    pixel): zl = the sum of min(z, z_out) over the measured (VALID, NOISY) pixels, il[0] their count,
    il[1] their outliers (z > z_out), il[2] the pixels not VALID, il[3] those of them already
    RECONSTRUCTED, il[4] the VALID ones that are not finite, il[5] the pixels not VALID whose past averages
    fewer than `reuse_frames` frames (unsettled). Branch-free over whole rows, so that it vectorises."""
    zero = np.float32(0.0)
    w = values.shape[1]
    ndg = nd * g
    ndf = nd * nd * floor
    for x in range(w):
        zl[x] = zero
    for k in range(6):
        for x in range(w):
            il[k, x] = 0
    for y in range(y0, y1):
        vr = values[y]
        sr = state[y]
        pr = prev[y]
        qr = var[y]
        cr = cnt[y]
        for x in range(w):
            st = sr[x]
            r = st & REASON_MASK
            m = (r == VALID) | (r == NOISY)
            p = pr[x]
            att = ((st & ATTENUATED) != 0) | (r == NOISY)
            lv = p if p > zero else zero
            vm = (ndg * lv + ndf) if att else (g * lv + floor)
            v = vr[x]
            d = v - p
            t = tol * p
            base = vm + qr[x] + t * t
            z = d * d / base
            zc = z if z < z_out else z_out
            zl[x] += zc if m else zero
            u = r != VALID
            il[0, x] += np.int32(m)
            il[1, x] += np.int32(m & (d * d > z_out * base))
            il[2, x] += np.int32(u)
            il[3, x] += np.int32(u & ((st & RECONSTRUCTED) != 0))
            il[4, x] += np.int32((r == VALID) & (not (abs(v) < np.inf)))
            il[5, x] += np.int32(u & (cr[x] < reuse_frames))


@njit(cache=True, nogil=True, inline="always")
def _lane_sums(zl, il, x0, x1):
    """The block x0..x1-1's sums of the lanes of `_still_rows`: (sum of min(z, z_out), measured, outliers,
    not VALID, of them RECONSTRUCTED, VALID not finite, unsettled)."""
    zs = np.float32(0.0)
    c0 = c1 = c2 = c3 = c4 = c5 = 0
    for i in range(x0, x1):
        zs += zl[i]
        c0 += il[0, i]
        c1 += il[1, i]
        c2 += il[2, i]
        c3 += il[3, i]
        c4 += il[4, i]
        c5 += il[5, i]
    return (zs, np.int64(c0), np.int64(c1), np.int64(c2), np.int64(c3), np.int64(c4), np.int64(c5))


@njit(cache=True, nogil=True, error_model="numpy", fastmath=FAST)
def _reuse_row(values, state, prev, var, cnt, work, y, fm, use_bounds, g, floor, nd, tol, z_out, max_frames,
               la, lv, lc):
    """Row y of the still REUSE blocks (fm[x] = 1 at their pixels) finished in place, branch-free: their
    past and output become the numbers `_prepare_px` and `_finish` give (measured and NOISY pixels
    averaged with their past, an outlier or a pixel whose past is a placeholder restarted from its
    measurement, the others their past within their bounds, RECONSTRUCTED; a clipped pixel at least its
    own value: the neighbours' bound was applied when it was reconstructed); `work` keeps the row's input
    values. The whole row is computed into the scratch lanes la, lv, lc (the caller's, the row's length),
    then selected, so that both loops are long and vectorise. Returns the pixels not VALID written."""
    zero = np.float32(0.0)
    ndg = nd * g
    ndf = nd * nd * floor
    flag = np.uint8(RECONSTRUCTED)
    vr = values[y]
    sr = state[y]
    pr = prev[y]
    qr = var[y]
    cr = cnt[y]
    wr = work[y]
    w = vr.shape[0]
    for x in range(w):
        st = sr[x]
        r = st & REASON_MASK
        v = vr[x]
        p = pr[x]
        vp = qr[x]
        n0 = np.int32(cr[x])
        meas = (r == VALID) | (r == NOISY)
        att = ((st & ATTENUATED) != 0) | (r == NOISY)
        lvl = p if p > zero else zero
        vm = (ndg * lvl + ndf) if att else (g * lvl + floor)
        lim = vm / max_frames
        vpp = vp if vp > lim else lim
        inv = np.float32(1.0) / (vm + vpp)
        a = (v * vpp + p * vm) * inv
        nv = vm * vpp * inv
        nv = nv if nv > lim else lim
        d = v - p
        t = tol * p
        fresh = not (vp < np.float32(np.inf))   # a placeholder past (a preview start): no frame averaged
        out = meas & ((d * d > z_out * (vm + vp + t * t)) | fresh)       # restarts from its measurement
        vo = v if v > zero else zero
        nvo = (ndg * vo + ndf) if att else (g * vo + floor)
        q = p
        q = v if use_bounds & (r == CLIPPED) & (v == v) & (v > q) else q
        q = v if use_bounds & (r == DARK) & (v == v) & (v < q) else q
        n1 = n0 + 1
        n1 = n1 if n1 < 255 else 255
        la[x] = v if out else (a if meas else q)
        lv[x] = nvo if out else (nv if meas else vp)
        lc[x] = np.uint8((n0 if (r == NOISY) & (not fresh) else 1) if out else (n1 if meas else n0))
    n = 0
    for x in range(w):
        f = fm[x] != 0
        st = sr[x]
        m = f & ((st & REASON_MASK) != VALID)
        v = vr[x]
        wr[x] = v
        pr[x] = la[x] if f else pr[x]
        qr[x] = lv[x] if f else qr[x]
        cr[x] = lc[x] if f else cr[x]
        vr[x] = la[x] if f else v
        sr[x] = st | (flag * np.uint8(m))
        n += np.int64(m)
    return n


@njit(cache=True, nogil=True, parallel=True)
def _reuse_late(values, state, prev, var, cnt, scratch, late, fast, bs, use_bounds, g, floor, nd, tol, z_out,
                max_frames):
    """The blocks `late` marks finished as `_judge_blocks` finishes a reused block (`_reuse_row`), after it;
    fast = 1 there. `scratch` (h, w) takes the rows' input values in place of `work` (which keeps the
    input of the frame). Returns the pixels not VALID written."""
    h, w = values.shape
    nby, nbx = late.shape
    n = 0
    for by in prange(nby):
        fm = np.zeros(w, np.uint8)
        k = 0
        for bx in range(nbx):
            if late[by, bx] != 0:
                fm[bx * bs:min(bx * bs + bs, w)] = 1
                fast[by, bx] = 1
                k += 1
        if k == 0:
            continue
        la = np.empty(w, np.float32)
        lv = np.empty(w, np.float32)
        lc = np.empty(w, np.uint8)
        c = 0
        for y in range(by * bs, min(by * bs + bs, h)):
            c += _reuse_row(values, state, prev, var, cnt, scratch, y, fm, use_bounds, g, floor, nd, tol, z_out,
                            max_frames, la, lv, lc)
        n += c
    return n


@njit(cache=True, nogil=True, parallel=True)
def _clip_lower_rows(values, state, lower, rows, bs):
    """lower[y, x] = the clipped-neighbour bound of the clipped regular pixels (`validity.clip_lower_row`,
    in the rows of the block rows `rows` marks that have one; elsewhere scratch)."""
    for y in prange(state.shape[0]):
        if rows[y // bs] != 0 and row_has_clipped_regular(state, y):
            clip_lower_row(values, state, y, lower[y])


@njit(cache=True, nogil=True, parallel=True)
def _undo_fast(values, state, work, fast, bs):
    """The input again in the blocks `_judge_blocks` finished (a cut, or a frame the single-frame path must
    judge): values from `work`, no RECONSTRUCTED bit on their missing pixels (they had none)."""
    h, w = values.shape
    keep = np.uint8(~RECONSTRUCTED & 0xFF)
    for y in prange(h):
        by = y // bs
        for x in range(w):
            if fast[by, x // bs] != 0:
                values[y, x] = work[y, x]
                st = state[y, x]
                state[y, x] = st if (st & REASON_MASK) == VALID else st & keep


@njit(cache=True, nogil=True, inline="always")
def _bounds_at(values, state, lower, y, x):
    """(lower, upper) bound of pixel (y, x) as `validity.bounds` gives them (NaN: none): a CLIPPED pixel
    at least its value, a clipped regular one at least its attenuated neighbours' smallest value when they
    are all clipped (`lower[y, x]` as `_clip_lower_rows` leaves it); a DARK pixel at most its value."""
    nan = np.float32(np.nan)
    st = state[y, x]
    r = st & REASON_MASK
    v = values[y, x]
    m = lower[y, x]
    lo = m if ((st & (ATTENUATED | REASON_MASK)) == CLIPPED) & (m == m) & (m > v) else v
    return (lo if r == CLIPPED else nan), (v if r == DARK else nan)


@njit(cache=True, nogil=True)
def _bounds_kept(values, state, prev, y0, y1, x0, x1, tol):
    """True when every pixel of the block is measured, CLIPPED with its past at or above its value or DARK
    with its past at or below it (within `tol`)."""
    lo = np.float32(1.0) - tol
    hi = np.float32(1.0) + tol
    for y in range(y0, y1):
        for x in range(x0, x1):
            r = state[y, x] & REASON_MASK
            v = values[y, x]
            p = prev[y, x]
            if r == CLIPPED:
                if not p >= v * lo:
                    return False
            elif r == DARK:
                if not p <= v * hi:
                    return False
            elif r != VALID and r != NOISY:
                return False
    return True


@njit(cache=True, nogil=True, inline="always")
def _prepare_px(v, st, p, vp, va, n_past, d, lb, ub, use_bounds, g, floor, nd, tol, z_out, max_frames):
    """One pixel of the reconstruction's input, given its block's decision d and its aligned past (p, vp,
    alignment variance va; vp inf: none, n_past frames): (work, pv, pvar, pc, known) (`_prepare_blocks`)."""
    inf = np.float32(np.inf)
    r = st & REASON_MASK
    att = (st & ATTENUATED) != 0
    known = r == VALID
    pvar = _meas_var(v, att, g, floor, nd) if known else inf
    if d == FRESH or d == NO_EVIDENCE or not vp < inf:
        return v, v, pvar, np.int32(0), known
    vp = vp + va
    if r == VALID or (d == REUSE and r == NOISY):
        vm = _meas_var(p, att or r == NOISY, g, floor, nd)
        dd = v - p
        t = tol * p
        if dd * dd > z_out * (vm + vp + t * t):                # an outlier: the pixel restarts
            if r == VALID:
                return v, v, pvar, np.int32(0), known
            # a NOISY one from its measurement, keeping its count (it is measured every frame: its
            # block stays settled)
            return v, v, -_meas_var(v, True, g, floor, nd), n_past - 1, True
        lim = vm / max_frames
        vpp = vp if vp > lim else lim
        inv = np.float32(1.0) / (vm + vpp)         # (as `_reuse_row`: the same numbers)
        a = (v * vpp + p * vm) * inv
        nv = vm * vpp * inv
        nv = nv if nv > lim else lim
        return a, a, (nv if r == VALID else -nv), n_past, True          # negative: a reused pixel, as it is
    if d == REUSE:
        if use_bounds:
            p = lb if (r == CLIPPED) & (lb == lb) & (lb > p) else p
            p = ub if (r == DARK) & (ub == ub) & (ub < p) else p
        return p, p, -vp, n_past - 1, True                              # (`_finish` adds the frame)
    if d == REFRESH:
        return v, p, vp, n_past, known
    return v, v, pvar, np.int32(0), known


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _prepare_blocks(blocks, values, state, prev, var, cnt, cy, cx, bs, dec, cand, known, lower, upper, use_bounds,
                    work, pv, pvar, pc, left, g, floor, nd, tol, z_out, max_frames, cmis):
    """The reconstruction's input in the blocks `blocks` ((by, bx) rows): known mask and bounds
    (`validity.bounds`' rules), `work` = the values with measured pixels of trusted blocks averaged with
    their aligned past (inverse variance; an outlier restarts its pixel), missing pixels of REUSE blocks =
    their past within their bounds and known (NOISY ones averaged with their measurement); pv / pvar = the
    aligned past where a missing pixel is to be fused with it (pvar inf: no past) or, at measured and
    reused pixels, the new value's variance (negative: reused); pc = the frames the past averages.
    left[i] = the pixels of block i left to reconstruct."""
    h, w = values.shape
    nan = np.float32(np.nan)
    for i in prange(blocks.shape[0]):
        by = blocks[i, 0]
        bx = blocks[i, 1]
        d = dec[by, bx]
        c = cand[by, bx]
        nl = 0
        for y in range(by * bs, min(by * bs + bs, h)):
            for x in range(bx * bs, min(bx * bs + bs, w)):
                st = state[y, x]
                lb = nan
                ub = nan
                if use_bounds:
                    lb, ub = _bounds_at(values, state, lower, y, x)
                    lower[y, x] = lb
                    upper[y, x] = ub
                if c == 0:                          # still: the past at the same pixel
                    p = prev[y, x]
                    vp = var[y, x]
                    va = np.float32(0.0)
                    n_past = np.int32(cnt[y, x])
                else:
                    p, vp, va = _aligned(prev, var, y, x, cy[c], cx[c], h, w, cmis[c])
                    n_past = _count_at(cnt, y, x, cy[c], cx[c], h, w)
                a, q, qv, n, k = _prepare_px(values[y, x], st, p, vp, va, n_past, d, lb, ub, use_bounds, g,
                                             floor, nd, tol, z_out, max_frames)
                work[y, x] = a
                pv[y, x] = q
                pvar[y, x] = qv
                pc[y, x] = n
                known[y, x] = k
                nl += 0 if k else 1
        left[i] = nl


@njit(cache=True, nogil=True, parallel=True)
def _fill_fast(blocks, prev, bs, work, known, lower, upper, use_bounds):
    """The blocks finished in the judgement as the reconstruction's known context: work = their new past."""
    h, w = work.shape
    nan = np.float32(np.nan)
    for i in prange(blocks.shape[0]):
        by = blocks[i, 0]
        bx = blocks[i, 1]
        for y in range(by * bs, min(by * bs + bs, h)):
            for x in range(bx * bs, min(bx * bs + bs, w)):
                work[y, x] = prev[y, x]
                known[y, x] = True
                if use_bounds:
                    lower[y, x] = nan
                    upper[y, x] = nan


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _finish(values, state, work, pv, pvar, pc, prev, var, cnt, fast, bs, lower, upper, use_bounds, g, rec_noise,
            rec_tol, reuse_frames, floor, rec_tex, nd, z_out):
    """Write the frame and keep it as the past, outside the blocks `_judge_blocks` finished (`fast`):
    measured pixels get their average, missing pixels the reconstruction fused by inverse
    variance with their aligned past (where they have one and it agrees within Z_OUT), within their
    bounds, with RECONSTRUCTED. The reconstruction's texture term (`_tex_var`) reads `work` around the
    pixel: `_reconstruct_left` has put the new past of the finished blocks next to a reconstructed one
    there. Returns the number of missing pixels written."""
    h, w = values.shape
    flag = np.uint8(RECONSTRUCTED)
    n = 0
    for y in prange(h):
        c = 0
        by = y // bs
        for x0 in range(0, w, bs):
            x1 = min(x0 + bs, w)
            if fast[by, x0 // bs] != 0:
                continue                                  # finished by `_judge_blocks`
            for x in range(x0, x1):
                st = state[y, x]
                r = st & REASON_MASK
                a = work[y, x]
                n1 = np.int32(pc[y, x]) + 1
                cnt[y, x] = np.uint8(n1 if n1 < 255 else 255)
                if r == VALID:
                    values[y, x] = a
                    prev[y, x] = a
                    var[y, x] = pvar[y, x]
                    continue
                vp = pvar[y, x]
                p = pv[y, x]
                if vp < np.float32(0.0):
                    values[y, x] = a                          # reused: the past as it is
                    state[y, x] = st | flag
                    prev[y, x] = a
                    var[y, x] = -vp
                    c += 1
                    continue
                vr = _rec_var(a, g, floor, rec_noise, rec_tol) + _tex_var(work, y, x, h, w, rec_tex)
                if r == NOISY:          # fused with its own measurement: no less certain than that
                    vm = _meas_var(a, True, g, floor, nd)
                    vr = vm if vm < vr else vr
                nv = vr
                if vp < np.float32(np.inf):
                    dd = a - p
                    if dd * dd > z_out * (vr + vp):
                        cnt[y, x] = 1                         # the past disagrees: the reconstruction alone
                    else:
                        a = (a * vp + p * vr) / (vr + vp)
                        if use_bounds:
                            lb = lower[y, x]
                            ub = upper[y, x]
                            a = lb if (r == CLIPPED) & (lb == lb) & (lb > a) else a
                            a = ub if (r == DARK) & (ub == ub) & (ub < a) else a
                        nv = vr * vp / (vr + vp)
                        lim = vr / reuse_frames
                        nv = nv if nv > lim else lim
                values[y, x] = a
                state[y, x] = st | flag
                prev[y, x] = a
                var[y, x] = nv
                c += 1
        n += c
    return n
