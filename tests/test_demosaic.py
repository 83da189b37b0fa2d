"""nrhdr_core.demosaic: joint reconstruction of missing photosites and missing colours of a Bayer mosaic."""
from __future__ import annotations

import numpy as np
import pytest

from nrhdr_core import cfa, demosaic
from nrhdr_core.states import CLIPPED, DARK, DISCARDED, RECONSTRUCTED, REASON_MASK, VALID

METHODS = demosaic.METHODS


def _masked(h, w, share, seed=0):
    rng = np.random.default_rng(seed)
    return np.where(rng.random((h, w)) < share, DISCARDED, VALID).astype(np.uint8)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("pattern", cfa.PATTERNS)
def test_constant_colour_and_measured_kept(method, pattern):
    h, w = 24, 30
    rgb = np.empty((3, h, w), np.float32)
    rgb[0], rgb[1], rgb[2] = 300.0, 120.0, 45.0
    m = cfa.mosaic(rgb, pattern)
    st = _masked(h, w, 0.4)
    st0 = st.copy()
    out = demosaic.reconstruct_cfa(m, st, pattern, method=method)
    assert out.shape == (3, h, w) and out.dtype == np.float32
    np.testing.assert_allclose(out, rgb, rtol=1e-5)
    idx = cfa.channel_index(pattern, h, w)
    known = st0 == VALID
    own = np.take_along_axis(out, idx[None].astype(np.intp), 0)[0]
    np.testing.assert_array_equal(own[known], m[known])
    np.testing.assert_array_equal(st, np.where(known, st0, st0 | RECONSTRUCTED))
