"""FSE fallback for pixels no block could fill (their support area held no usable pixel) and for frames
without a usable model: the value of the nearest source pixel (:func:`fill_left`, by the project's one
nearest fill, :func:`nrhdr_core.fill.nearest_at`), the bounds when no pixel is known
(:func:`fill_without_data`), the bounds around a constant (:func:`fill_bounded`).
"""
from __future__ import annotations

import numpy as np

from ..fill import coords, nearest_at
from .params import KNOWN, MISSING, NOISY, RECONSTRUCTED

__all__ = ["fill_left", "fill_without_data", "fill_bounded"]

# sources by working state: known, reconstructed, noisy measurement; not missing nor skipped
_STATE_SRC = np.zeros(256, np.bool_)
_STATE_SRC[[KNOWN, RECONSTRUCTED, NOISY]] = True
_STATE_LEFT = np.zeros(256, np.bool_)
_STATE_LEFT[MISSING] = True


def fill_left(work, state):
    """The pixels no block could fill (MISSING) get the value of the nearest known, reconstructed or
    noisy-measurement pixel (`nrhdr_core.fill`'s rule; none anywhere: 0) and become RECONSTRUCTED;
    returns their coordinates (row-major)."""
    ys, xs = coords(state, _STATE_LEFT)
    nearest_at(work, work, state, _STATE_SRC, state, _STATE_LEFT, ys, xs)
    state[ys, xs] = RECONSTRUCTED
    return ys, xs


def fill_without_data(out, miss, lower, upper):
    """No pixel known: the ``miss`` pixels of ``out`` get 0 raised to ``lower`` and lowered to ``upper``
    where those are finite."""
    fill = np.zeros(out.shape, np.float32)
    if lower is not None:
        lo = np.broadcast_to(np.asarray(lower, np.float32), out.shape)
        m = np.isfinite(lo)
        fill[m] = np.maximum(fill[m], lo[m])
    if upper is not None:
        hi = np.broadcast_to(np.asarray(upper, np.float32), out.shape)
        m = np.isfinite(hi)
        fill[m] = np.minimum(fill[m], hi[m])
    out[miss] = fill[miss]
    return out


def fill_bounded(out, miss, lower, upper):
    """The ``miss`` pixels of ``out`` clamped to ``lower``/``upper`` where those are finite (None: unbounded)."""
    if lower is not None:
        lo = np.broadcast_to(np.asarray(lower, np.float32), out.shape)
        m = miss & np.isfinite(lo)
        out[m] = np.maximum(out[m], lo[m])
    if upper is not None:
        hi = np.broadcast_to(np.asarray(upper, np.float32), out.shape)
        m = miss & np.isfinite(hi)
        out[m] = np.minimum(out[m], hi[m])
    return out
