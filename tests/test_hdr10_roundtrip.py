"""HDR10 / HLG delivery: the BT.2390 EETF and the content light levels against formulas written out here, and
`nrhdr hdr10` round trips: a small clip encoded with x265 (lossless, so every decoded code is the encoded one),
decoded by ffmpeg (an independent decoder) to yuv420p10le, PQ / HLG inverted here and compared with the chain's
OpenEXR radiance within the 10-bit quantisation step (after the EETF where it applies); the signalling as
ffprobe reads it from the stream, its SEI and the container (MP4 and Matroska)."""
from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from conftest import make_test_clip

ROOT = Path(__file__).resolve().parents[1]
W, H, N = 128, 96, 4

# SMPTE ST 2084 / ARIB STD-B67 as published (ITU-R BT.2100 Tables 4 and 5)
m1, m2 = 2610 / 16384, 2523 / 4096 * 128
c1, c2, c3 = 3424 / 4096, 2413 / 4096 * 32, 2392 / 4096 * 32
a_, b_, c_ = 0.17883277, 0.28466892, 0.55991073


def pq_inv(nits):
    y = np.clip(np.asarray(nits, float) / 10000.0, 0, 1)
    return ((c1 + c2 * y ** m1) / (1 + c3 * y ** m1)) ** m2


def pq_eotf(sig):
    p = np.clip(np.asarray(sig, float), 0, 1) ** (1 / m2)
    return 10000.0 * (np.maximum(p - c1, 0) / (c2 - c3 * p)) ** (1 / m1)


def hlg_inv(sig):
    s = np.clip(np.asarray(sig, float), 0, 1)
    return np.where(s <= 0.5, s * s / 3, (np.exp((s - c_) / a_) + b_) / 12)


def eetf(L, src_peak, dst_peak):
    """ITU-R BT.2390-10 section 5.4.1, black 0: Hermite roll-off in normalised PQ."""
    e1 = np.minimum(pq_inv(L) / pq_inv(src_peak), 1.0)
    max_lum = pq_inv(dst_peak) / pq_inv(src_peak)
    ks = 1.5 * max_lum - 0.5
    t = (e1 - ks) / (1 - ks)
    p = (2 * t**3 - 3 * t**2 + 1) * ks + (t**3 - 2 * t**2 + t) * (1 - ks) + (-2 * t**3 + 3 * t**2) * max_lum
    return pq_eotf(np.where(e1 > ks, p, e1) * pq_inv(src_peak)), pq_eotf(ks * pq_inv(src_peak))


# ---- core ------------------------------------------------------------------------------------------------

def test_eetf_bt2390():
    from nrhdr_core.tonemap import eetf_BT2390
    L = np.geomspace(0.01, 1289.0, 400)
    exp, knee = eetf(L, 1289.0, 1000.0)
    np.testing.assert_allclose(eetf_BT2390(L, 1289.0, 1000.0), exp, rtol=1e-9)
    assert 500 < knee < 1000
    below = L <= knee
    np.testing.assert_allclose(exp[below], L[below], rtol=1e-9)      # identity below the knee
    assert exp[-1] == pytest.approx(1000.0, rel=1e-9)                   # the source peak lands on the target
    assert (np.diff(exp) > 0).all()                                     # monotone: no banding reversal
    np.testing.assert_allclose(eetf_BT2390(L, 800.0, 1000.0), L.clip(max=1000.0))   # nothing to roll off


@pytest.mark.parametrize("transfer", ["pq", "hlg"])
def test_hdr_encode_rolls_off_to_the_peak(transfer):
    from nrhdr_core.tonemap import hdr_encode, hlg_reference_E, peak_luminance
    diffuse, white = 4094.0, 4094.0 * 6.35
    v = np.geomspace(1.0, white, 3000).astype(np.float32)[None]
    src = peak_luminance(white, diffuse, transfer)
    out = hdr_encode(v, diffuse, transfer, peak=1000.0, source_peak=src) >> 6
    plain = hdr_encode(v, diffuse, transfer) >> 6
    if transfer == "pq":
        assert src == pytest.approx(203.0 * 6.35)
        L = v[0].astype(float) / diffuse * 203.0
        exp, knee = eetf(L, src, 1000.0)
        sig = pq_inv(exp)
    else:
        E = v[0].astype(float) / diffuse * hlg_reference_E(203.0)
        L = 1000.0 * E ** 1.2
        assert src == pytest.approx(L[-1], rel=1e-6)
        exp, knee = eetf(L, src, 1000.0)
        e = np.clip((exp / 1000.0) ** (1 / 1.2), 0, 1)
        sig = np.where(e <= 1 / 12, np.sqrt(3 * e), a_ * np.log(np.maximum(12 * e - b_, 1e-12)) + c_)
    code_max = math.floor(64 + 876 * (pq_inv(1000.0) if transfer == "pq" else 1.0) + 1e-9)
    exp_codes = np.minimum(np.floor(64 + 876 * sig + 0.5), code_max)
    assert np.abs(out[0] - exp_codes).max() <= 1                       # float32 input, float64 formulas
    assert out.max() == code_max                                       # the top reaches the peak, no clip
    assert np.array_equal(out[0][L < knee * 0.98], plain[0][L < knee * 0.98])   # unchanged below the knee
    assert (np.diff(out[0].astype(int)) >= 0).all()


def test_mastering_display_and_light_level_forms():
    from nrhdr_core import hdr_output as h
    md = h.MasteringDisplay("bt2020", 1000.0, 0.005)
    assert md.caps_field() == "35400:14600:8500:39850:6550:2300:15635:16450:10000000:50"
    assert md.caps_field(5).endswith(":50000000:250")
    assert md.x265() == "G(8500,39850)B(6550,2300)R(35400,14600)WP(15635,16450)L(10000000,50)"
    assert h.MasteringDisplay("p3").caps_field().startswith("34000:16000:13250:34500:7500:3000:")
    with pytest.raises(ValueError, match="primaries"):
        h.MasteringDisplay("srgb")
    with pytest.raises(ValueError, match="MaxFALL"):
        h.content_light_caps_field(100, 200)
    assert h.container_of("a/b.MKV") == "mkv" and h.container_of("x.mp4") == "mp4" and h.container_of("x") is None


def test_light_levels_measured_from_codes():
    from nrhdr_core.hdr_output import LightLevels
    rng = np.random.default_rng(1)
    frames = [(rng.integers(64, 700, (6, 9)) << 6).astype(np.uint16) for _ in range(3)]
    frames[1][2, 3] = 800 << 6
    ll = LightLevels("pq")
    for f in frames:
        ll.update(f)
    nits = [pq_eotf(((f >> 6) - 64) / 876.0) for f in frames]
    assert ll.max_cll == math.ceil(pq_eotf((800 - 64) / 876.0))
    assert ll.max_fall_int == math.ceil(max(n.mean() for n in nits))


def test_hdr_png_still_has_cicp(tmp_path):
    from nrhdr_core import hdr_output, io
    oiio = pytest.importorskip("OpenImageIO")
    codes = (np.arange(64, 941, dtype=np.uint16) << 6).reshape(1, -1).repeat(3, 0)
    for transfer, tc in (("pq", 16), ("hlg", 18)):
        p = io.write_hdr_png(tmp_path / f"{transfer}.png", hdr_output.full_range16(codes), transfer)
        inp = oiio.ImageInput.open(str(p))
        assert tuple(inp.spec().getattribute("CICP")) == (9, tc, 0, 1)
        inp.close()
        img = io.read_image(p, np.uint16)[..., 0]
        np.testing.assert_array_equal(img[0], np.floor((np.arange(64, 941) - 64) * 65535 / 876 + 0.5))
    with pytest.raises(ValueError, match="png"):
        io.write_hdr_png(tmp_path / "x.tif", codes, "pq")


# ---- round trips -------------------------------------------------------------------------------------------

def _tools():
    if shutil.which("ffmpeg") is None or shutil.which("ffprobe") is None:
        pytest.skip("ffmpeg/ffprobe not installed (Debian: ffmpeg)")
    if subprocess.run(["gst-inspect-1.0", "--exists", "x265enc"]).returncode != 0:
        pytest.skip("x265enc not installed (Debian: gstreamer1.0-plugins-bad)")


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return make_test_clip(tmp_path_factory.mktemp("hdr10") / "clip", width=W, height=H, frames=N, fps=5)


@pytest.fixture(scope="module")
def exr_radiance(clip, tmp_path_factory):
    """The chain's linear frames as OpenEXR (what nrexrsink / nrhdr batch write), read back."""
    from nrhdr_core import chain, io
    d, prof, raws = clip
    out = tmp_path_factory.mktemp("exr")
    s = chain.ChainSettings(method="nearest")
    frames = []
    for i, raw in enumerate(raws):
        v, st = chain.process_frame(raw.copy(), prof, s)
        io.write_exr(out / f"frame_{i:05d}.exr", v, st)
        frames.append(io.read_exr(out / f"frame_{i:05d}.exr")[0])
    return np.stack(frames).astype(np.float64)


def hdr10(env, clip_dir, out, *extra):
    p = subprocess.run([sys.executable, "-m", "gst_plugins.cli", "hdr10", str(clip_dir), str(out),
                        "--method", "nearest", "--no-progress", *extra], env=env, capture_output=True, text=True,
                       timeout=300)
    return p.returncode, p.stdout + p.stderr


def decode_y(path):
    """ffmpeg to yuv420p10le (bit-exact codes, limited range kept): the Y planes, (N, H, W) uint16."""
    raw = subprocess.run(["ffmpeg", "-v", "error", "-i", str(path), "-f", "rawvideo", "-pix_fmt", "yuv420p10le",
                          "-"], capture_output=True, check=True).stdout
    per = W * H + 2 * (W // 2) * (H // 2)
    a = np.frombuffer(raw, "<u2").reshape(-1, per)
    assert np.all(a[:, W * H:] == 512)                                  # grey: neutral chroma
    return a[:, :W * H].reshape(-1, H, W)


def probe(path):
    s = json.loads(subprocess.run(["ffprobe", "-v", "error", "-select_streams", "v:0", "-show_streams", "-of",
                                   "json", str(path)], capture_output=True, check=True, text=True).stdout)
    f = json.loads(subprocess.run(["ffprobe", "-v", "error", "-select_streams", "v:0", "-read_intervals", "%+#1",
                                   "-show_frames", "-of", "json", str(path)],
                                  capture_output=True, check=True, text=True).stdout)
    return s["streams"][0], f["frames"][0]


def side(items, kind):
    return next((x for x in items.get("side_data_list", []) if x["side_data_type"] == kind), None)


@pytest.mark.gst
@pytest.mark.parametrize("suffix", ["mp4", "mkv"])
def test_hdr10_round_trip_and_signalling(gst_subprocess_env, clip, exr_radiance, tmp_path, suffix):
    _tools()
    d, prof, raws = clip
    out = tmp_path / f"out.{suffix}"
    rc, text = hdr10(gst_subprocess_env, d, out, "--x265-options", "lossless=1")
    assert rc == 0, text
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]     # no temporaries, no out.mkv.mkv

    # decoded codes -> display light (PQ inverted here) against the EXR radiance through the documented mapping
    y = decode_y(out).astype(np.float64)
    assert y.shape == (N, H, W)
    diffuse = float(prof.regular_white)
    L_true = np.maximum(exr_radiance, 0) / diffuse * 203.0               # cd/m2: diffuse white at 203
    src_peak = float(prof.white) / diffuse * 203.0
    L_disp, knee = eetf(L_true, src_peak, 1000.0)
    code_max = math.floor(64 + 876 * pq_inv(1000.0))
    exact = np.minimum(64 + 876 * pq_inv(L_disp), code_max)            # the unrounded code of each pixel
    assert np.abs(y - exact).max() <= 0.5 + 1e-3                       # within half a 10-bit step
    # the same in radiance: below the knee the decoded radiance brackets the EXR's by the step around it
    lin = L_true <= knee
    rad = lambda c: pq_eotf((c - 64) / 876.0) / 203.0 * diffuse        # noqa: E731
    bright = lin & (y > 64)
    assert (rad(y[bright] - 0.5 - 1e-3) <= exr_radiance[bright]).all()
    assert (exr_radiance[bright] <= rad(y[bright] + 0.5 + 1e-3)).all()
    assert lin.mean() > 0.5 and (~lin).any()                           # both regions are exercised

    stream, frame = probe(out)
    assert (stream["profile"], stream["pix_fmt"]) == ("Main 10", "yuv420p10le")
    assert (stream["color_primaries"], stream["color_transfer"], stream["color_space"], stream["color_range"]) \
        == ("bt2020", "smpte2084", "bt2020nc", "tv")
    # the measured light levels: from the decoded codes, computed here
    nits = pq_eotf((y - 64) / 876.0)
    cll = (math.ceil(nits.max() - 1e-9), math.ceil(nits.mean(axis=(1, 2)).max() - 1e-9))
    for where in (frame,) + ((stream,) if suffix == "mkv" else ()):     # SEI; Matroska's Colour element
        md = side(where, "Mastering display metadata")
        assert md is not None, where
        assert Fraction(md["max_luminance"]) == 1000 and Fraction(md["min_luminance"]) == Fraction(5, 1000)
        assert (Fraction(md["red_x"]), Fraction(md["green_y"]), Fraction(md["white_point_x"])) \
            == (Fraction(708, 1000), Fraction(797, 1000), Fraction(3127, 10000))
        light = side(where, "Content light level metadata")
        assert (light["max_content"], light["max_average"]) == cll
    assert cll[0] <= 1000


@pytest.mark.gst
def test_hlg_round_trip(gst_subprocess_env, clip, exr_radiance, tmp_path):
    from nrhdr_core.tonemap import hlg_reference_E
    _tools()
    d, prof, raws = clip
    out = tmp_path / "hlg.mkv"
    rc, text = hdr10(gst_subprocess_env, d, out, "--transfer", "hlg", "--x265-options", "lossless=1")
    assert rc == 0, text
    y = decode_y(out).astype(np.float64)
    diffuse = float(prof.regular_white)
    E = np.maximum(exr_radiance, 0) / diffuse * hlg_reference_E(203.0)     # scene light, 203 cd/m2 at 75 %
    L, knee = eetf(1000.0 * E ** 1.2, 1000.0 * (float(prof.white) / diffuse * hlg_reference_E(203.0)) ** 1.2,
                   1000.0)
    e = np.clip((L / 1000.0) ** (1 / 1.2), 0, 1)
    sig = np.where(e <= 1 / 12, np.sqrt(3 * e), a_ * np.log(np.maximum(12 * e - b_, 1e-12)) + c_)
    assert np.abs(y - (64 + 876 * sig)).max() <= 0.5 + 1e-3
    lin = (1000.0 * E ** 1.2 <= knee) & (y > 64)
    e_dec = hlg_inv((y[lin] - 64) / 876.0)
    np.testing.assert_allclose(e_dec, E[lin], rtol=0.02, atol=1e-5)    # HLG step: < 2 % of E above 1/12
    stream, frame = probe(out)
    assert (stream["color_primaries"], stream["color_transfer"], stream["color_space"], stream["color_range"]) \
        == ("bt2020", "arib-std-b67", "bt2020nc", "tv")
    assert side(frame, "Mastering display metadata") is None           # HLG: no static metadata


@pytest.mark.gst
def test_lossy_default_quality(gst_subprocess_env, clip, exr_radiance, tmp_path):
    """The default constant quality against the EXR frames in log2 terms, with the bitrate it takes."""
    from nrhdr_core import metrics
    _tools()
    d, prof, raws = clip
    out = tmp_path / "q.mp4"
    rc, text = hdr10(gst_subprocess_env, d, out)
    assert rc == 0, text
    assert "kbit/s" in text and "MaxCLL" in text
    y = decode_y(out).astype(np.float64)
    diffuse = float(prof.regular_white)
    rad = pq_eotf((y - 64) / 876.0) / 203.0 * diffuse
    L_true = np.maximum(exr_radiance, 0) / diffuse * 203.0
    ok = L_true <= eetf(L_true, float(prof.white) / diffuse * 203.0, 1000.0)[1]   # the linear part
    floor = diffuse * 1e-3
    err = np.abs(np.log2(np.maximum(rad[ok], floor)) - np.log2(np.maximum(exr_radiance[ok], floor)))
    assert np.median(err) < 0.1 and np.percentile(err, 99) < 1.0, (np.median(err), np.percentile(err, 99))
    assert metrics.log2_psnr(np.maximum(exr_radiance[ok], floor), np.maximum(rad[ok], floor), floor=floor) > 30


@pytest.mark.gst
def test_output_rules_and_stills(gst_subprocess_env, clip, tmp_path):
    from nrhdr_core import io
    _tools()
    d, prof, raws = clip
    out = tmp_path / "o.mkv"
    out.write_bytes(b"keep")
    rc, text = hdr10(gst_subprocess_env, d, out)
    assert rc == 2 and "already exists" in text and "--force" in text
    assert out.read_bytes() == b"keep"
    stills = tmp_path / "stills"
    rc, text = hdr10(gst_subprocess_env, d, stills)
    assert rc == 0, text
    files = sorted(stills.glob("frame_*.png"))
    assert len(files) == N
    oiio = pytest.importorskip("OpenImageIO")
    inp = oiio.ImageInput.open(str(files[0]))
    assert tuple(inp.spec().getattribute("CICP")) == (9, 16, 0, 1)
    inp.close()
    img = io.read_image(files[0], np.uint16)
    assert img.shape == (H, W, 1) and img.max() > img.min()
