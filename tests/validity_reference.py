"""Plain-Python statement of the clipped-neighbour bound of `validity.bounds` / `validity.prepare`, for the
tests to check the numba pass against."""
from __future__ import annotations

import numpy as np

from nrhdr_core.states import ATTENUATED, CLIPPED, REASON_MASK


def clip_lower_bound(values, state, lower):
    """Raise, in place, the lower bound of every clipped regular pixel whose attenuated pixels in its 3 x 3
    neighbourhood (5 x 5 when the 3 x 3 has none) are all clipped to the smallest of their values: light
    that saturates the ND pixels around it saturates it at least as much. Returns `lower`."""
    h, w = state.shape
    for y in range(h):
        for x in range(w):
            st = state[y, x]
            if st & ATTENUATED or (st & REASON_MASK) != CLIPPED:
                continue
            for r in (1, 2):
                win = (slice(max(y - r, 0), y + r + 1), slice(max(x - r, 0), x + r + 1))
                att = (state[win] & ATTENUATED) != 0
                if att.any():
                    if np.all((state[win][att] & REASON_MASK) == CLIPPED):
                        m = np.float32(values[win][att].min())
                        if not (lower[y, x] >= m):
                            lower[y, x] = m
                    break
    return lower
