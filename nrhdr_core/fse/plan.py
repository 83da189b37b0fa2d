"""FSE block plan: the quadtree leaves of every tile and the rounds of mutually independent tiles.

A tile is a ``max_block`` square; its quadtree (Genser et al., IWSSIP 2017) splits a block while the sigma
of its support area is above ``split_sigma`` (integral images give that sigma in O(1)); only leaves with a
missing pixel are kept. The processing order (Genser et al., PCS 2018) groups the tiles into rounds whose
tiles are never adjacent, so a round's tiles can run on any thread in any order and read only pixels of
earlier rounds: the result does not depend on the thread count.
"""
from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from .params import KNOWN, MISSING, NOISY

__all__ = ["Plan", "block_plan", "integral_images", "quadtree_leaves", "rounds"]

# tile_round: round of every tile (-1: nothing missing); tshift: log2(tile); tw_tiles: tiles per row;
# round_ptr/round_tiles: the tiles of round r are round_tiles[round_ptr[r]:round_ptr[r + 1]];
# leaf_ptr: the leaves of tile t are leaf_*[leaf_ptr[t]:leaf_ptr[t + 1]]; leaf_y/leaf_x: top-left corner;
# leaf_lvl: quadtree level (block size Tables.sizes[leaf_lvl])
Plan = namedtuple("Plan", "tile_round tshift tw_tiles round_ptr round_tiles leaf_ptr leaf_y leaf_x leaf_lvl")


def block_plan(work, state, p, tab, scale) -> Plan:
    """Step 3 of the frame (``reconstruct``; Genser et al.): quadtree leaves per tile (only leaves with
    missing pixels) and the round of every tile, for parameters ``p`` and tables ``tab``
    (``params.tables``)."""
    tile = int(p["max_block"])
    h, w = state.shape
    miss = _missing_per_tile(state, tile)
    leaf_ptr, leaf_y, leaf_x, leaf_lvl = quadtree_leaves(work, state, tile, int(p["window"]), tab.sizes,
                                                         tab.split, scale, miss)
    tile_round, round_ptr, round_tiles, _nr = rounds(miss, h, w, tile, float(p["edge_penalty"]),
                                                     int(p["order_levels"]), int(p["order_slack"]))
    tshift = int(round(math.log2(tile)))
    return Plan(tile_round, tshift, (w + tile - 1) // tile, round_ptr, round_tiles, leaf_ptr, leaf_y,
                leaf_x, leaf_lvl)


@njit(cache=True, nogil=True)
def integral_images(img, state):
    """Integral images (count, sum, sum of squares) of the known pixels: the area sigma of any support
    area in O(1) for the quadtree split (Genser et al.)."""
    h, w = img.shape
    c = np.zeros((h + 1, w + 1), np.float64)
    s1 = np.zeros((h + 1, w + 1), np.float64)
    s2 = np.zeros((h + 1, w + 1), np.float64)
    for y in range(h):
        rc = 0.0
        r1 = 0.0
        r2 = 0.0
        for x in range(w):
            if state[y, x] == KNOWN:
                v = np.float64(img[y, x])
                rc += 1.0
                r1 += v
                r2 += v * v
            c[y + 1, x + 1] = c[y, x + 1] + rc
            s1[y + 1, x + 1] = s1[y, x + 1] + r1
            s2[y + 1, x + 1] = s2[y, x + 1] + r2
    return c, s1, s2


@njit(cache=True, nogil=True, inline="always")
def _box(a, y0, x0, y1, x1):
    return a[y1, x1] - a[y0, x1] - a[y1, x0] + a[y0, x0]


@njit(cache=True, nogil=True)
def _area_sigma(c, s1, s2, y, x, b, n, scale):
    """Std of the known pixels of the N x N support area of block (y, x, b), relative to ``scale``."""
    h = c.shape[0] - 1
    w = c.shape[1] - 1
    o = (n - b) // 2
    y0 = max(y - o, 0)
    x0 = max(x - o, 0)
    y1 = min(y - o + n, h)
    x1 = min(x - o + n, w)
    if y1 <= y0 or x1 <= x0:
        return 0.0
    cnt = _box(c, y0, x0, y1, x1)
    if cnt < 2.0:
        return 0.0
    m = _box(s1, y0, x0, y1, x1) / cnt
    var = _box(s2, y0, x0, y1, x1) / cnt - m * m
    if var < 0.0:
        var = 0.0
    return math.sqrt(var) / scale


@njit(cache=True, nogil=True)
def _missing_per_tile(state, tile):
    """Pixels needing the model (missing or noisy measurement) of every tile, row-major tiles."""
    h, w = state.shape
    tw = (w + tile - 1) // tile
    miss = np.zeros(((h + tile - 1) // tile) * tw, np.int64)
    for y in range(h):
        base = (y // tile) * tw
        for tx in range(tw):
            c = 0
            for x in range(tx * tile, min(tx * tile + tile, w)):
                st = state[y, x]
                c += 1 if (st == MISSING or st == NOISY) else 0
            miss[base + tx] += c
    return miss


@njit(cache=True, nogil=True)
def _any_missing(state, y, x, b):
    h, w = state.shape
    for yy in range(y, min(y + b, h)):
        for xx in range(x, min(x + b, w)):
            st = state[yy, xx]
            if st == MISSING or st == NOISY:
                return True
    return False


@njit(cache=True, nogil=True)
def quadtree_leaves(img, state, tile, n, sizes, split, scale, miss):
    """Quadtree leaves of every tile, depth-first in z-order (Genser et al.: a block of size b is a leaf
    when the sigma of its support area is below split[b], else it is split down to the smallest size);
    only blocks with a missing pixel are kept: blocks with nothing missing cost nothing.
    Returns (leaf_ptr, leaf_y, leaf_x, leaf_lvl)."""
    h, w = state.shape
    tw = (w + tile - 1) // tile
    nt = miss.shape[0]
    need_sigma = False
    for i in range(sizes.shape[0] - 1):
        if split[i] > 0.0:
            need_sigma = True
    if need_sigma:
        c, s1, s2 = integral_images(img, state)
    else:
        c = np.zeros((1, 1))
        s1 = c
        s2 = c
    cap = 16
    for t in range(nt):
        if miss[t] > 0:
            cap += (tile // sizes[sizes.shape[0] - 1]) ** 2
    leaf_y = np.empty(cap, np.int64)
    leaf_x = np.empty(cap, np.int64)
    leaf_l = np.empty(cap, np.int64)
    leaf_ptr = np.zeros(nt + 1, np.int64)
    sy = np.empty(4 * 64, np.int64)
    sx = np.empty(4 * 64, np.int64)
    sl = np.empty(4 * 64, np.int64)
    nl = 0
    for t in range(nt):
        leaf_ptr[t] = nl
        if miss[t] == 0:
            continue
        sy[0] = (t // tw) * tile
        sx[0] = (t % tw) * tile
        sl[0] = 0
        sp = 1
        while sp > 0:
            sp -= 1
            y = sy[sp]
            x = sx[sp]
            lv = sl[sp]
            b = sizes[lv]
            if y >= h or x >= w or not _any_missing(state, y, x, b):
                continue
            leaf = lv == sizes.shape[0] - 1
            if not leaf and split[lv] > 0.0:
                leaf = _area_sigma(c, s1, s2, y, x, b, n, scale) < split[lv]
            if leaf:
                leaf_y[nl] = y
                leaf_x[nl] = x
                leaf_l[nl] = lv
                nl += 1
            else:
                hb = b // 2
                # push in reverse so that the top-left child is processed first
                sy[sp] = y + hb
                sx[sp] = x + hb
                sy[sp + 1] = y + hb
                sx[sp + 1] = x
                sy[sp + 2] = y
                sx[sp + 2] = x + hb
                sy[sp + 3] = y
                sx[sp + 3] = x
                for q in range(4):
                    sl[sp + q] = lv + 1
                sp += 4
    leaf_ptr[nt] = nl
    return leaf_ptr, leaf_y[:nl], leaf_x[:nl], leaf_l[:nl]


@njit(cache=True, nogil=True)
def rounds(miss, h, w, tile, edge_penalty, levels, slack):
    """Processing order by neighbour availability (Genser et al., PCS 2018): a tile's priority is the
    missing share of its 3 x 3 tile neighbourhood (not yet reconstructed; out-of-image neighbours count
    ``edge_penalty``), quantised to ``levels``; a round is a greedy set of mutually non-adjacent tiles
    with level <= lowest + ``slack``, so its tiles are independent. Returns (tile_round, round_ptr,
    round_tiles, n_rounds)."""
    th = (h + tile - 1) // tile
    tw = (w + tile - 1) // tile
    nt = th * tw
    tile_round = np.full(nt, -1, np.int64)
    rem = 0
    for t in range(nt):
        if miss[t] > 0:
            tile_round[t] = -2
            rem += 1
    cur = np.zeros(nt, np.float64)
    for t in range(nt):
        ty = t // tw
        tx = t % tw
        area = min(tile, h - ty * tile) * min(tile, w - tx * tile)
        cur[t] = miss[t] / area
    lvl = np.zeros(nt, np.int64)
    in_round = np.zeros(nt, np.bool_)
    round_tiles = np.empty(max(rem, 1), np.int64)
    round_ptr = np.zeros(rem + 2, np.int64)
    r = 0
    k = 0
    while rem > 0:
        lmin = 1 << 60
        for t in range(nt):
            if tile_round[t] != -2:
                continue
            ty = t // tw
            tx = t % tw
            p = 0.0
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy = ty + dy
                    xx = tx + dx
                    if yy < 0 or yy >= th or xx < 0 or xx >= tw:
                        p += edge_penalty
                    else:
                        p += cur[yy * tw + xx]
            lv = int(p / 9.0 * levels)
            lvl[t] = lv
            if lv < lmin:
                lmin = lv
        round_ptr[r] = k
        for t in range(nt):
            if tile_round[t] != -2 or lvl[t] > lmin + slack:
                continue
            ty = t // tw
            tx = t % tw
            ok = True
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy = ty + dy
                    xx = tx + dx
                    if 0 <= yy < th and 0 <= xx < tw and in_round[yy * tw + xx]:
                        ok = False
            if ok:
                in_round[t] = True
                round_tiles[k] = t
                k += 1
        for i in range(round_ptr[r], k):
            t = round_tiles[i]
            in_round[t] = False
            tile_round[t] = r
            cur[t] = 0.0
            rem -= 1
        r += 1
    round_ptr[r] = k
    return tile_round, round_ptr[: r + 1], round_tiles[:k], r
