"""`nrhdr hdr10 --report` (docs/HDR-OUTPUT.md "Measuring an encode"): the report helpers of
nrhdr_core.hdr_output against expectations written out here (ST 2084, the BT.2087 matrix, BT.2020 Y'CbCr), a
known per-channel code offset through ffmpeg, and the command on colour and grey clips (lossless x265: the
decode scores what was sent). Tests that need ffmpeg or x265enc skip with the reason when they are missing,
except under CI=true, where they fail."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from nrhdr_core import hdr_output, tonemap

DIFFUSE, WHITE = 4094.0, 4094.0 * 6.35


def need(tool: str, what: str) -> None:
    """Skip (fail under CI=true) when `tool` is missing."""
    missing = (shutil.which(tool) is None if tool in ("ffmpeg", "ffprobe") else
               shutil.which("gst-inspect-1.0") is None
               or subprocess.run(["gst-inspect-1.0", "--exists", tool]).returncode != 0)
    if missing:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"{tool} is missing (required under CI=true)")
        pytest.skip(f"{tool} not installed ({what})")


def pq_signal(nits):
    """SMPTE ST 2084 inverse EOTF, constants as published."""
    m1, m2 = 2610 / 16384, 2523 / 4096 * 128
    c1, c2, c3 = 3424 / 4096, 2413 / 4096 * 32, 2392 / 4096 * 32
    y = np.clip(np.asarray(nits, np.float64) / 10000.0, 0, 1) ** m1
    return ((c1 + c2 * y) / (1 + c3 * y)) ** m2


BT2087 = np.array([[0.6274, 0.3293, 0.0433], [0.0691, 0.9195, 0.0114], [0.0164, 0.0880, 0.8956]])


# ---- helpers -------------------------------------------------------------------------------------------------
def test_code_light_and_light_code_are_st2084():
    """Whole codes give code_luminance's light; light_code is 64 + 876 PQ(L) and inverts code_light."""
    codes = np.arange(64, 941)
    np.testing.assert_allclose(hdr_output.code_light(codes), hdr_output.code_luminance()[codes], rtol=1e-12)
    nits = np.array([0.0, 0.1, 1.0, 100.0, 203.0, 1000.0, 10000.0])
    np.testing.assert_allclose(hdr_output.light_code(nits), 64 + 876 * pq_signal(nits), atol=1e-9)
    np.testing.assert_allclose(hdr_output.light_code(hdr_output.code_light(codes[:-1] + 0.25)), codes[:-1] + 0.25,
                               atol=1e-6)
    for tr in tonemap.TRANSFERS:       # (PQ's black is a signal of 7e-7, not 0)
        np.testing.assert_allclose(hdr_output.light_code(hdr_output.code_light(codes, tr), tr), codes, atol=1e-3)
    with pytest.raises(ValueError, match="transfer"):
        hdr_output.code_light(codes, "gamma")


def test_display_reference_rgb_is_what_hdr_encode_rgb_quantises():
    """The codes of hdr_encode_rgb are the rounded exact codes of display_reference_rgb (within half a code;
    with the roll-off, the last code at or below the peak); a pure BT.709 red goes through the BT.2087 matrix
    (written out here) and the white balance."""
    rng = np.random.default_rng(3)
    rgb = (rng.random((3, 24, 32)) ** 3 * 3 * WHITE).astype(np.float32)
    gains = (1.25, 1.0, 0.8)
    for transfer in tonemap.TRANSFERS:
        for peak in (0.0, 1000.0):
            sp = tonemap.peak_luminance(WHITE, DIFFUSE, transfer)
            codes = tonemap.hdr_encode_rgb(rgb, DIFFUSE, transfer, gains, peak=peak, source_peak=sp) >> 6
            light = hdr_output.display_reference_rgb(rgb, DIFFUSE, transfer, gains, peak=peak, source_peak=sp)
            err = codes - hdr_output.light_code(light, transfer)
            assert np.abs(err).max() <= (0.5 + 1e-6 if peak == 0 else 1.0), (transfer, peak)
    red = np.zeros((3, 1, 1), np.float32)
    red[0] = 1000.0
    light = hdr_output.display_reference_rgb(red, DIFFUSE, "pq", (1.5, 1.0, 1.0))
    scale = 1500.0 / DIFFUSE * 203.0              # the matrix's published 4 decimals: within 5e-5 each
    np.testing.assert_allclose(light[:, 0, 0], BT2087[:, 0] * scale, rtol=0, atol=5e-5 * scale)


def test_grey_reference_is_the_monochrome_one():
    v = np.geomspace(1, 3 * WHITE, 12 * 16).astype(np.float32).reshape(12, 16)
    for transfer in tonemap.TRANSFERS:
        sp = tonemap.peak_luminance(WHITE, DIFFUSE, transfer)
        rgb = hdr_output.display_reference_rgb(np.stack([v, v, v]), DIFFUSE, transfer, peak=1000.0, source_peak=sp)
        grey = hdr_output.display_reference(v, DIFFUSE, transfer, peak=1000.0, source_peak=sp)
        np.testing.assert_allclose(rgb, np.stack([grey] * 3), rtol=1e-9, atol=1e-9)


def ycbcr_written_out(codes):
    """BT.2020 NCL Y'CbCr 4:2:0 of R'G'B' codes (3, H, W), written out: Y' per pixel, chroma of two rows
    averaged and filtered [1, 2, 1] / 4 along the row (co-sited), rounded to 10-bit narrow range."""
    e = (codes.astype(np.float64) - 64) / 876
    kr, kb = 0.2627, 0.0593
    y = kr * e[0] + (1 - kr - kb) * e[1] + kb * e[2]
    cb, cr = (e[2] - y) / 1.8814, (e[0] - y) / 1.4746
    out = [np.floor(64 + 876 * y + 0.5)]
    for c in (cb, cr):
        rows = (c[0::2] + c[1::2]) / 2
        pad = np.pad(rows, ((0, 0), (1, 1)), mode="edge")
        sub = (pad[:, 0:-2] + 2 * pad[:, 1:-1] + pad[:, 2:]) / 4
        out.append(np.floor(512 + 896 * sub[:, 0::2] + 0.5))
    return out


def test_ycbcr420_round_trip():
    """ycbcr420_planes is the BT.2020 NCL 4:2:0 written out here; rgb_from_ycbcr420 gives a flat colour back
    within the rounding of Y', Cb, Cr (1.5 codes), a grey picture exactly."""
    rng = np.random.default_rng(5)
    codes = np.empty((3, 16, 24), np.uint16)
    codes[:] = rng.integers(100, 900, (3, 1, 1))
    y, cb, cr = hdr_output.ycbcr420_planes(codes, shift=0)
    for got, want in zip((y, cb, cr), ycbcr_written_out(codes)):
        np.testing.assert_array_equal(got, want)
    assert np.abs(hdr_output.rgb_from_ycbcr420(y, cb, cr) - codes).max() <= 1.5
    grey = np.broadcast_to(rng.integers(64, 941, (1, 16, 24)), (3, 16, 24)).astype(np.uint16)
    np.testing.assert_allclose(hdr_output.rgb_from_ycbcr420(*hdr_output.ycbcr420_planes(grey, shift=0)), grey,
                               atol=1e-9)
    with pytest.raises(ValueError, match="4:2:0"):
        hdr_output.rgb_from_ycbcr420(y, cb[:, :-1], cr)


def test_quality_report_shows_a_channel_offset_in_that_channel():
    """Codes +6 in G only: G's mean code error is +6, R's and B's 0, the luminance's between (G weighs 0.678
    in it), CIEDE2000 grows from 0; exact codes score zero error and infinite PSNR."""
    rng = np.random.default_rng(7)
    codes = rng.integers(300, 700, (2, 3, 8, 10)).astype(np.float64)
    ref = hdr_output.code_light(codes)
    exact = hdr_output.quality_report(ref, ref)
    assert set(exact) == {"R", "G", "B", "Y", "ciede2000"}
    assert all(exact[c]["code_error_abs_max"] < 1e-6 and exact[c]["log2_psnr"] == np.inf for c in "RGBY")
    assert exact["ciede2000"]["mean"] < 1e-6
    shifted = codes.copy()
    shifted[:, 1] += 6
    rep = hdr_output.quality_report(ref, hdr_output.code_light(shifted))
    assert rep["G"]["code_error_mean"] == pytest.approx(6, abs=1e-6)
    assert abs(rep["R"]["code_error_mean"]) < 1e-6 and abs(rep["B"]["code_error_mean"]) < 1e-6
    assert 1.0 < rep["Y"]["code_error_mean"] < 6.0
    assert rep["ciede2000"]["mean"] > 0.5
    assert rep["G"]["log2_psnr"] < rep["Y"]["log2_psnr"]
    grey = hdr_output.quality_report(ref[:, 1], hdr_output.code_light(shifted[:, 1]))
    assert set(grey) == {"Y"} and grey["Y"]["code_error_mean"] == pytest.approx(6, abs=1e-6)


def test_ciede2000_scores_only_up_to_the_reference_white():
    """The CIELAB white is the reference white: a grey at it has L* = 100 (against black: dE00 100), pixels
    brighter than it are left out, and their share is reported."""
    ref = np.zeros((3, 1, 4))
    ref[:, 0, 1] = 203.0
    ref[:, 0, 2] = 500.0
    ref[:, 0, 3] = [150.0, 50.0, 50.0]
    test = ref.copy()
    test[:, 0, 1] = 0.0
    test[:, 0, 2] = 0.0                    # above the white: not scored
    de = hdr_output.ciede2000_scores(ref, test, 203.0)
    assert de["share"] == pytest.approx(0.75)
    assert de["mean"] == pytest.approx(100.0 / 3, rel=1e-6)
    assert hdr_output.ciede2000_scores(ref + 10, ref + 10, 1.0)["mean"] is None


# ---- through ffmpeg -------------------------------------------------------------------------------------------
def encode_decode(tmp_path, codes, name):
    """R'G'B' codes (N, 3, H, W) as 4:2:0 Y'CbCr (ycbcr420_planes) into a lossless FFV1 file by ffmpeg, then
    decoded by `nrhdr hdr10 --report`'s decoder: (N, 3, H, W) R'G'B' code values."""
    from gst_plugins.cli import hdr
    n, _, h, w = codes.shape
    raw = tmp_path / f"{name}.yuv"
    with open(raw, "wb") as f:
        for c in codes:
            for p in hdr_output.ycbcr420_planes(c.astype(np.uint16), shift=0):
                f.write(np.ascontiguousarray(p, "<u2").tobytes())
    out = tmp_path / f"{name}.mkv"
    subprocess.run(["ffmpeg", "-v", "error", "-f", "rawvideo", "-pix_fmt", "yuv420p10le", "-s", f"{w}x{h}", "-r", "5",
                    "-i", str(raw), "-c:v", "ffv1", "-pix_fmt", "yuv420p10le", str(out)], check=True)
    y, cb, cr = hdr.decode_planes(out, w, h)
    return np.stack([hdr_output.rgb_from_ycbcr420(*p) for p in zip(y, cb, cr)])


def test_lossless_video_scores_near_zero_and_an_offset_shows_in_its_channel(tmp_path):
    """Uniform colour frames through ffmpeg losslessly score within the Y'CbCr rounding (1.5 codes, mean
    under half a code), 8 codes more green a visible colour difference; random colours with G 8 codes higher
    show +8 in G and nothing in R and B, beside the same pictures without the offset."""
    need("ffmpeg", "Debian: ffmpeg")
    colours = np.array([[700, 300, 500], [200, 600, 400], [512, 512, 512]])
    codes = np.broadcast_to(colours[:, :, None, None], (3, 3, 16, 24)).astype(np.float64)
    ref = hdr_output.code_light(codes)
    base = hdr_output.quality_report(ref, hdr_output.code_light(encode_decode(tmp_path, codes, "base")))
    for c in "RGBY":
        assert base[c]["code_error_abs_max"] <= 1.5 and base[c]["code_error_abs_mean"] < 0.5, (c, base[c])
    assert base["ciede2000"]["mean"] < 0.5
    greener = codes.copy()
    greener[:, 1] += 8
    de = hdr_output.quality_report(ref, hdr_output.code_light(encode_decode(tmp_path, greener, "greener")))
    assert de["ciede2000"]["mean"] > base["ciede2000"]["mean"] + 0.5
    # pictures of random colours (each pixel's Y'CbCr rounding its own: the means carry the offset alone)
    codes = np.random.default_rng(11).integers(200, 800, (2, 3, 32, 48)).astype(np.float64)
    ref = hdr_output.code_light(codes)
    base = hdr_output.quality_report(ref, hdr_output.code_light(encode_decode(tmp_path, codes, "random")))
    shifted = codes.copy()
    shifted[:, 1] += 8
    rep = hdr_output.quality_report(ref, hdr_output.code_light(encode_decode(tmp_path, shifted, "g8")))
    assert rep["G"]["code_error_mean"] - base["G"]["code_error_mean"] == pytest.approx(8, abs=0.1)
    for c in "RB":
        assert abs(rep[c]["code_error_mean"] - base[c]["code_error_mean"]) < 0.1, c


# ---- the command ----------------------------------------------------------------------------------------------
LINE = re.compile(r"^  (.+?)\s+([RGBY])\s+(\S+) /\s+(\S+) dB\s+code error (\S+) / (\S+) / (\S+)$")


def parse_report(text: str) -> dict:
    """{(section, row, channel): (PU21, log2, mean, mean abs, max abs)} and {(section, row): dE00 mean}."""
    rows, de, section = {}, {}, None
    for line in text.splitlines():
        if line.startswith("against "):
            section = "truth" if "truth" in line else "chain"
        m = LINE.match(line)
        if m:
            rows[(section, m.group(1), m.group(2))] = tuple(float(x) for x in m.groups()[2:])
        m = re.match(r"^  (.+?)\s+CIEDE2000 mean (\S+),", line)
        if m:
            de[(section, m.group(1))] = float(m.group(2))
    return rows, de


def cli(env, *args):
    p = subprocess.run([sys.executable, "-m", "gst_plugins.cli", *map(str, args)], env=env, capture_output=True,
                       text=True, timeout=900)
    return p.returncode, p.stdout + p.stderr


@pytest.mark.gst
def test_hdr10_report_colour_clip_lossless(gst_subprocess_env, tmp_path):
    """A colour clip encoded losslessly: the 10-bit R'G'B' within a code of the chain's light (half a code and
    the cap at the peak's code), the decode exactly what was sent (the 4:2:0 Y'CbCr rows), CIEDE2000 and the
    truth's section present; a lossy encode of the same clip scores below the lossless one."""
    need("ffmpeg", "Debian: ffmpeg")
    need("x265enc", "Debian: gstreamer1.0-plugins-bad")
    clip = tmp_path / "clip"
    rc, text = cli(gst_subprocess_env, "simulate", "synthetic", "-o", clip, "--cfa", "rggb", "--frames", 2, "--width",
                   64, "--height", 48)
    assert rc == 0, text
    rc, text = cli(gst_subprocess_env, "hdr10", clip, tmp_path / "c.mp4", "--method", "preview", "--no-progress",
                   "--x265-options", "lossless=1", "--report")
    assert rc == 0, text
    rows, de = parse_report(text)
    for c in "RGBY":
        assert rows[("chain", "10-bit R'G'B'", c)][4] <= 1.0, text
        assert rows[("chain", "decoded", c)] == rows[("chain", "4:2:0 Y'CbCr", c)], text
        assert ("truth", "the chain", c) in rows and ("truth", "decoded", c) in rows, text
    assert de[("chain", "10-bit R'G'B'")] < 1.0 and ("truth", "decoded") in de, text
    rc, lossy = cli(gst_subprocess_env, "hdr10", clip, tmp_path / "l.mp4", "--method", "preview", "--no-progress",
                    "--crf", 40, "--report")
    assert rc == 0, lossy
    worse = parse_report(lossy)[0]
    assert worse[("chain", "decoded", "Y")][3] > rows[("chain", "decoded", "Y")][3], lossy


@pytest.mark.gst
def test_hdr10_report_grey_clip_lossless(gst_subprocess_env, tmp_path):
    """A grey clip losslessly: the decoded codes are the 10-bit codes (the same scores, within half a code)."""
    need("ffmpeg", "Debian: ffmpeg")
    need("x265enc", "Debian: gstreamer1.0-plugins-bad")
    clip = tmp_path / "clip"
    rc, text = cli(gst_subprocess_env, "simulate", "synthetic", "-o", clip, "--frames", 2, "--width", 64,
                   "--height", 48)
    assert rc == 0, text
    rc, text = cli(gst_subprocess_env, "hdr10", clip, tmp_path / "m.mkv", "--method", "preview", "--no-progress",
                   "--x265-options", "lossless=1", "--report")
    assert rc == 0, text
    rows, de = parse_report(text)
    assert rows[("chain", "decoded", "Y")] == rows[("chain", "10-bit codes", "Y")], text
    assert rows[("chain", "decoded", "Y")][4] <= 1.0 and not de, text
    assert ("truth", "decoded", "Y") in rows and not any(k[2] in "RGB" for k in rows), text


def test_hdr10_report_refusals(tmp_path, capsys, monkeypatch):
    """--report with PNG stills, or without ffmpeg: refused before any work, naming the option."""
    from gst_plugins.cli import main
    from nrhdr_core import simulate
    from nrhdr_core import profile as profiles
    clip = tmp_path / "clip"
    prof = profiles.default(16, 24, seed=1, cfa="rggb")
    simulate.simulate_clip(simulate.synthetic_rgb_scene(), clip, prof, frames=1, progress=False)
    assert main(["hdr10", str(clip), str(tmp_path / "stills"), "--report", "--no-progress"]) == 2
    assert "--report scores a video" in capsys.readouterr().err
    assert not (tmp_path / "stills").exists()
    real = shutil.which
    monkeypatch.setattr(shutil, "which", lambda name, *a, **k: None if name == "ffmpeg" else real(name, *a, **k))
    assert main(["hdr10", str(clip), str(tmp_path / "v.mp4"), "--report", "--no-progress"]) == 2
    assert "--report decodes the video with ffmpeg, which is not installed" in capsys.readouterr().err
    assert not list(tmp_path.glob("v.mp4*"))
