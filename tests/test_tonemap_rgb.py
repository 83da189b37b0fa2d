"""The colour SDR tone map `tonemap.tonemap_rgb` (docs/TONEMAP.md "Colour") against the documented formula written
out here in float64: white balance, luminance through the grey operator (log or local) to a 16-bit level,
(c / L)^s Y in linear display light, out-of-gamut colours mixed with their grey, sRGB codes rounded in the
encoded domain."""
from __future__ import annotations

import numpy as np
import pytest

from nrhdr_core import tonemap

H, W = 61, 97
KR, KB = 0.2126, 0.0722


def varied_frame(seed=0):
    """Linear camera RGB over ~16 stops: random chroma (some nearly primary, out of gamut once bright), a few
    grey, black, negative and non-finite pixels."""
    rng = np.random.default_rng(seed)
    lum = np.exp2(rng.uniform(-2, 15, (H, W)))
    ch = rng.uniform(0.05, 1.0, (3, H, W))
    vivid = rng.uniform(size=(H, W)) < 0.2
    ch[:, vivid] = rng.choice([1e-3, 1.0], size=(3, int(vivid.sum())))
    rgb = (ch / (KR * ch[0] + (1 - KR - KB) * ch[1] + KB * ch[2]) * lum).astype(np.float32)
    rgb[:, 0, :5] = 0.0
    rgb[:, 1, :5] = rgb[1, 1, :5]                                     # grey
    rgb[0, 2, 0], rgb[1, 2, 1], rgb[2, 2, 2], rgb[0, 2, 3] = np.nan, -4.0, np.inf, 1e35
    return rgb


def srgb_eotf(v):
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def reference(rgb, white, gains, exposure, contrast, sat, operator="log"):
    """float64 codes of the documented colour tone map: the luminance's 16-bit level from the grey `operator`."""
    c32 = [np.minimum(np.nan_to_num(rgb[i] * np.float32(g), nan=0.0, posinf=1e30, neginf=0.0).clip(0, None),
                      np.float32(1e30)).astype(np.float32) for i, g in enumerate(gains)]
    r, g, b = c32
    lum = g + np.float32(KR) * (r - g) + np.float32(KB) * (b - g)        # the luminance the grey operator sees
    if operator == "log":
        level = tonemap.log_tonemap(lum, white, exposure, contrast, dtype=np.uint16)
    else:
        level = tonemap.LocalTonemap()(lum, white, exposure, contrast, dtype=np.uint16)
    y = srgb_eotf(level / 65535.0)
    L = lum.astype(np.float64)
    lit = L > 0
    t = np.stack([np.where(lit, (c.astype(np.float64) / np.where(lit, L, 1.0)) ** sat * y, y) for c in c32])
    mx = t.max(axis=0)
    over = mx > 1.0
    f = np.where(over, (1.0 - y) / np.where(over, mx - y, 1.0), 1.0)
    t = np.clip(y + (t - y) * f, 0.0, 1.0)
    thresholds = srgb_eotf((np.arange(255) + 0.5) / 255.0)               # code k+1 from the middle of k, k+1 on
    return np.searchsorted(thresholds, t, side="right").transpose(1, 2, 0)


@pytest.mark.parametrize("sat", [1.0, 0.6, 1.5])
@pytest.mark.parametrize("gains,exposure,contrast", [((1.0, 1.0, 1.0), 0.0, 1000.0), ((1.3, 1.0, 0.8), 0.7, 300.0)])
def test_log_codes_follow_the_documented_formula(sat, gains, exposure, contrast):
    rgb = varied_frame()
    got = tonemap.tonemap_rgb(rgb, 3e3, "log", gains, exposure, contrast, sat).astype(int)
    want = reference(rgb, 3e3, gains, exposure, contrast, sat)
    diff = np.abs(got - want)
    assert diff.max() <= 1                                  # float32 against float64 at a rounding boundary
    assert (diff == 0).mean() > 0.995


@pytest.mark.parametrize("sat", [1.0, 0.6])
@pytest.mark.parametrize("gains,exposure,contrast", [((1.0, 1.0, 1.0), 0.0, 1000.0), ((1.3, 1.0, 0.8), 0.7, 300.0)])
def test_local_codes_follow_the_documented_formula(sat, gains, exposure, contrast):
    """The local operator: the grey local operator's level of the luminance (a width that is no multiple of
    the 4-pixel cell: the last partial cell's pixels too), shown in colour as for log."""
    rgb = varied_frame(3)
    got = tonemap.LocalTonemap().rgb(rgb, 3e3, exposure, contrast, gains, sat).astype(int)
    want = reference(rgb, 3e3, gains, exposure, contrast, sat, "local")
    diff = np.abs(got - want)
    assert diff.max() <= 1                                  # float32 against float64 at a rounding boundary
    assert (diff == 0).mean() > 0.995


@pytest.mark.parametrize("operator", tonemap.SDR_OPERATORS)
def test_saturation_one_agrees_with_the_general_path(operator):
    """saturation 1 (no power) against the power path at the next float32 above 1."""
    rgb = varied_frame(1)
    one = tonemap.tonemap_rgb(rgb, 3e3, operator, (1.2, 1.0, 0.9))
    near = tonemap.tonemap_rgb(rgb, 3e3, operator, (1.2, 1.0, 0.9), saturation=float(np.nextafter(np.float32(1),
                                                                                                   np.float32(2))))
    diff = np.abs(one.astype(int) - near)
    assert diff.max() <= 1 and (diff == 0).mean() > 0.999


@pytest.mark.parametrize("operator", tonemap.SDR_OPERATORS)
def test_padded_output_rows_get_the_same_codes(operator):
    """nrtonemap writes into the mapped frame, whose rows may be padded."""
    rgb = varied_frame(2)
    want = tonemap.tonemap_rgb(rgb, 3e3, operator)
    buf = np.full((H, W * 3 + 7), 77, np.uint8)
    tonemap.tonemap_rgb(rgb, 3e3, operator, out=buf[:, :W * 3].reshape(H, W, 3))
    np.testing.assert_array_equal(buf[:, :W * 3].reshape(H, W, 3), want)
    assert (buf[:, W * 3:] == 77).all()


@pytest.mark.parametrize("operator", tonemap.SDR_OPERATORS)
def test_grey_codes_are_exact(operator):
    """A grey pixel of a power-of-two value shows exactly its level's display light Y' (c / L = 1, no rounding),
    so its code is the number of float32 code thresholds srgb_eotf((k + 0.5) / 255) at or below float32 Y':
    no tolerance, over many levels."""
    rng = np.random.default_rng(4)
    grey = np.exp2(rng.integers(-12, 17, (H, W))).astype(np.float32)
    thresholds = srgb_eotf((np.arange(255) + 0.5) / 255.0).astype(np.float32)
    for white in (1.0, 37.0, 3e3, 5e4):
        if operator == "log":
            level = tonemap.log_tonemap(grey, white, dtype=np.uint16)
        else:
            level = tonemap.LocalTonemap()(grey, white, dtype=np.uint16)
        want = np.searchsorted(thresholds, srgb_eotf(level / 65535.0).astype(np.float32), side="right")
        got = tonemap.tonemap_rgb(np.stack([grey] * 3), white, operator)
        for ch in range(3):
            np.testing.assert_array_equal(got[..., ch], want)


@pytest.mark.parametrize("width", [1, 3, 4, 6, 8, W])
def test_local_statistics_equal_the_grey_operators_on_the_luminance(width):
    """The colour local operator's frame statistics (c, g, offset) are the grey operator's on the frame's float32
    luminance, bit for bit: the cell moments are summed alike for full and partial 4-pixel cells."""
    rgb = np.ascontiguousarray(varied_frame(5)[:, :, :width])
    gains = (1.3, 1.0, 0.8)
    c = [np.minimum(np.nan_to_num(rgb[i] * np.float32(g), nan=0.0, posinf=1e30, neginf=0.0).clip(0, None),
                    np.float32(1e30)).astype(np.float32) for i, g in enumerate(gains)]
    lum = c[1] + np.float32(KR) * (c[0] - c[1]) + np.float32(KB) * (c[2] - c[1])
    colour, grey = tonemap.LocalTonemap(), tonemap.LocalTonemap()
    colour.rgb(rgb, 3e3, 0.4, 300.0, gains)
    grey(lum, 3e3, 0.4, 300.0)
    np.testing.assert_array_equal(colour.params, grey.params)
