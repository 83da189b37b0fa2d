"""TMQI (Yeganeh and Wang 2013) against the values of the authors' TMQI.m v1.0 (GNU Octave 7.3) on the test
input of ../shared/docs/hdr-references.md."""
import math

import numpy as np
import pytest

from nrhdr_core import metrics


def _inputs(h=240, w=320):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    base = 10.0 ** (4.0 * xx / (w - 1) - 2.0)
    tex = 1.0 + 0.5 * np.sin(xx / 3.1) * np.cos(yy / 4.7) + 0.3 * np.sin((xx + 2 * yy) / 11.3)
    spot = 50.0 * np.exp(-((xx - 0.3 * w) ** 2 + (yy - 0.4 * h) ** 2) / (2 * 9.0 ** 2))
    hdr = base * tex + spot
    lg = np.log10(hdr)
    ldr = np.round(255.0 * (lg - lg.min()) / (lg.max() - lg.min()))
    return hdr, ldr


HDR, LDR = _inputs()


@pytest.mark.parametrize("hdr, ldr, ref", [
    (HDR, LDR, (0.875816935632, 0.922002577192, 0.348595993794)),
    (HDR, np.clip(np.round(255 * HDR / np.percentile(HDR, 99)), 0, 255),
     (0.698858277078, 0.6313787363, 0.00194046335578)),
    (HDR[:233, :301], LDR[:233, :301], (0.882366410951, 0.919045045365, 0.387385376486)),
], ids=["log", "clipped-linear", "odd-size"])
def test_matches_reference_release(hdr, ldr, ref):
    q, s, n = metrics.tmqi(hdr, ldr)
    assert q == pytest.approx(ref[0], abs=1e-7)
    assert s == pytest.approx(ref[1], abs=1e-7)
    assert n == pytest.approx(ref[2], rel=1e-9)


def test_constant_ldr_has_exactly_zero_local_variance():
    # TMQI.m: Q 0.140565 from E[x^2] - mu^2 rounding noise; exact centred variance: S = the C1 floor
    q, s, n = metrics.tmqi(HDR, np.full_like(HDR, 128.0))
    assert n == pytest.approx(0.0073468732189, rel=1e-9)
    assert q == pytest.approx(0.2174, abs=1e-4)
    # per scale: sigma_ldr = 0 -> p2 = Phi(-3), sigma12 = 0 -> second factor 1; p1 ~ 1 where HDR varies
    p2 = 0.5 * (1 + math.erf(-3 / 2 ** 0.5))
    assert s == pytest.approx((2 * p2 + 0.01) / (1 + p2 * p2 + 0.01), rel=0.02)


def test_scale_invariant_in_hdr_and_better_for_the_better_ldr():
    assert metrics.tmqi(HDR * 1e3, LDR) == pytest.approx(metrics.tmqi(HDR, LDR), abs=1e-6)
    blurred = np.round(0.5 * (LDR + np.roll(LDR, 3, axis=1)))
    assert metrics.tmqi(HDR, blurred)[1] < metrics.tmqi(HDR, LDR)[1]


def test_bad_inputs():
    with pytest.raises(ValueError, match="shape"):
        metrics.tmqi(HDR, LDR[:, :10])
    with pytest.raises(ValueError, match="finite"):
        metrics.tmqi(np.where(HDR > 100, np.nan, HDR), LDR)
    with pytest.raises(ValueError, match="inverted"):
        metrics.tmqi(HDR, 255 - LDR)
    with pytest.raises(ValueError, match="too small"):
        metrics.tmqi(HDR[:100, :100], LDR[:100, :100])
