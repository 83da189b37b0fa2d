"""classify (paper Eq. 3, section 2.3), every selection mode and dark policy: against a plain numpy statement
of the rules, on codes at and around every threshold."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from nrhdr_core import profile, sensor, validity


def _reference(raw, p, mode, dark_policy):
    """The rules written out in numpy: clipped at clip_code (value = lower bound (clip - black) * s); in
    'threshold' mode attenuated pixels below l_min (x WEIGHTED_LEVEL when weighted) are DARK with the
    threshold * s as upper bound, or, weighted, NOISY with their measurement when at or above SNR 0 dB and
    DARK with l_min * ND below; in 'all' and 'best' mode every pixel below SNR 0 dB is DARK, and in 'best' a
    VALID attenuated pixel with a VALID regular pixel among its 8 neighbours is DISCARDED."""
    att = p.mask
    s = np.where(att, np.float32(p.nd), np.float32(1.0))
    sig = raw.astype(np.float32) - np.float32(p.black_level)
    s0 = np.float32(sensor.zero_db_signal_dn(p))
    clipped = raw >= p.clip_code
    if mode == "threshold":
        thr = np.where(att, np.float32(p.l_min * (validity.WEIGHTED_LEVEL if dark_policy == "weighted" else 1)),
                       np.float32(-np.inf))
    else:
        thr = np.full(raw.shape, s0, np.float32)
    dark = ~clipped & (sig < thr)
    values = sig * s
    values[dark] = (thr * s)[dark]
    reason = np.where(clipped, validity.CLIPPED, np.where(dark, validity.DARK, validity.VALID))
    if mode == "threshold" and dark_policy == "weighted":
        noisy = dark & att & (sig >= s0)
        values[dark & att & ~noisy] = np.float32(p.l_min) * np.float32(p.nd)
        values[noisy] = (sig * s)[noisy]
        reason = np.where(noisy, validity.NOISY, reason)
    values[clipped] = ((np.float32(p.clip_code) - np.float32(p.black_level)) * s)[clipped]
    if mode == "best":
        near = ndimage.maximum_filter(~att & (reason == validity.VALID), size=3, mode="constant", cval=False)
        reason = np.where(att & (reason == validity.VALID) & near, validity.DISCARDED, reason)
    return values.astype(np.float32), (reason | np.where(att, validity.ATTENUATED, 0)).astype(np.uint8)


@pytest.mark.parametrize("mode", ["threshold", "all", "best"])
@pytest.mark.parametrize("policy", ["threshold", "weighted"])
def test_classify_matches_the_rules(mode, policy):
    p = profile.default(48, 64, seed=2, black_level=64.0)
    rng = np.random.default_rng(7)
    s0 = sensor.zero_db_signal_dn(p)
    near = np.array([0, 63, 64, 65, 64 + s0 - 1, 64 + s0, 64 + s0 + 1, 64 + p.l_min - 1, 64 + p.l_min,
                     64 + 4 * p.l_min - 1, 64 + 4 * p.l_min, 64 + 4 * p.l_min + 1, p.clip_code - 1, p.clip_code,
                     p.clip_code + 1, 4095])
    raw = np.where(rng.random(p.mask.shape) < 0.5, rng.choice(near, p.mask.shape),
                   rng.integers(0, 4096, p.mask.shape)).astype(np.uint16)
    v, s = validity.classify(raw, p, mode=mode, dark_policy=policy)
    ev, es = _reference(raw, p, mode, policy)
    np.testing.assert_array_equal(s, es)
    np.testing.assert_array_equal(v, ev)
    if policy == "weighted" and mode == "threshold":
        assert np.any((s & validity.REASON_MASK) == validity.NOISY)
