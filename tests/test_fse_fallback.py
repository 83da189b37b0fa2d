"""FSE's fallback for blocks whose support held no usable pixel (`fse._nearest_fill`): every left pixel
takes the value of a source pixel at the Euclidean-nearest distance, checked against scipy's exact
distance transform; both branches (ring search for few pixels, the transform for many)."""
import numpy as np
import pytest
from scipy import ndimage

from nrhdr_core import fse


def _check(work, left, src, got):
    s = ~left if src is None else src
    if not s.any():
        assert (got[left] == 0).all()
        return
    dist = ndimage.distance_transform_edt(~s)
    sy, sx = np.nonzero(s)
    for y, x in zip(*np.nonzero(left)):
        d2 = (sy - y) ** 2 + (sx - x) ** 2
        same = work[sy, sx] == got[y, x]            # the sources holding the value it took
        assert same.any() and d2[same].min() == round(dist[y, x] ** 2)
    assert np.array_equal(got[~left], work[~left])


@pytest.mark.parametrize("ring_max", [10**9, 0])   # ring search, scipy's transform
def test_nearest_fill_takes_a_nearest_source(ring_max, rng, monkeypatch):
    monkeypatch.setattr(fse, "NEAREST_RING_MAX", ring_max)
    for trial in range(60):
        h, w = rng.integers(1, 40, 2)
        work = rng.random((h, w)).astype(np.float32)
        left = rng.random((h, w)) < rng.random() * 0.5
        src = None if trial % 3 == 0 else (~left) & (rng.random((h, w)) < rng.random())
        got = work.copy()
        fse._nearest_fill(got, left, src)
        _check(work, left, src, got)


def test_nearest_fill_far_source():
    """One source in a corner of a 300 x 200 frame, a left pixel in the opposite corner."""
    work = np.zeros((200, 300), np.float32)
    work[0, 0] = 7.0
    src = np.zeros_like(work, bool)
    src[0, 0] = True
    left = np.zeros_like(src)
    left[199, 299] = True
    fse._nearest_fill(work, left, src)
    assert work[199, 299] == 7.0
