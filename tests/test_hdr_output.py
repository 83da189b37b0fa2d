"""HDR display output: SMPTE ST 2084 (PQ) and ARIB STD-B67 / BT.2100 HLG against the
published formulas and constants (written out here, independently of nrhdr_core.tonemap), nrtonemap
transfer=pq|hlg with BT.2100 colorimetry, and the shipped HDR pipelines."""
from __future__ import annotations

import math
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import hdr_buffer, run_appsrc

ROOT = Path(__file__).resolve().parents[1]

# SMPTE ST 2084 as published (ITU-R BT.2100 Table 4)
m1, m2 = 2610 / 16384, 2523 / 4096 * 128
c1, c2, c3 = 3424 / 4096, 2413 / 4096 * 32, 2392 / 4096 * 32
# ARIB STD-B67 (BT.2100 Table 5)
a, b, c = 0.17883277, 0.28466892, 0.55991073


def pq(nits):
    y = min(max(nits / 10000.0, 0.0), 1.0)
    return ((c1 + c2 * y ** m1) / (1 + c3 * y ** m1)) ** m2


def hlg(e):
    e = min(max(e, 0.0), 1.0)
    return math.sqrt(3 * e) if e <= 1 / 12 else a * math.log(12 * e - b) + c


def narrow10(sig):
    return int(math.floor(64 + 876 * sig + 0.5))


# ---- core ------------------------------------------------------------------------------------------------

def test_constants_as_published():
    from nrhdr_core import tonemap as t
    assert (t.M_1, t.M_2, t.C_1, t.C_2, t.C_3) == (0.1593017578125, 78.84375, 0.8359375, 18.8515625, 18.6875)
    assert t.HLG_A == a and abs(t.HLG_B - b) < 1e-8 and abs(t.HLG_C - c) < 1e-8


def test_pq_known_points():
    from nrhdr_core.tonemap import eotf_ST2084, eotf_inverse_ST2084
    # hand-computed / tabulated: 0 -> c1^m2, 100 cd/m2 -> 0.5081, 1000 -> 0.7518, 10000 -> 1
    pts = {0.0: c1 ** m2, 100.0: 0.508078, 203.0: 0.580689, 1000.0: 0.751827, 10000.0: 1.0}
    for nits, sig in pts.items():
        assert eotf_inverse_ST2084(nits) == pytest.approx(sig, abs=2e-6), nits
        assert eotf_inverse_ST2084(nits) == pytest.approx(pq(nits), rel=1e-12), nits
    x = np.geomspace(0.01, 10000, 50)
    np.testing.assert_allclose(eotf_ST2084(eotf_inverse_ST2084(x)), x, rtol=1e-9)
    assert eotf_inverse_ST2084(20000.0) == 1.0


def test_hlg_known_points():
    from nrhdr_core.tonemap import hlg_reference_E, oetf_HLG, oetf_inverse_HLG
    assert oetf_HLG(0.0) == 0.0
    assert oetf_HLG(1 / 12) == pytest.approx(0.5, abs=1e-12)       # the two segments meet at E' = 0.5
    assert oetf_HLG(1.0) == pytest.approx(1.0, abs=1e-7)
    for e in (0.001, 0.05, 0.2, 0.5, 0.9):
        assert oetf_HLG(e) == pytest.approx(hlg(e), abs=1e-8)
    np.testing.assert_allclose(oetf_inverse_HLG(oetf_HLG(np.linspace(0, 1, 41))), np.linspace(0, 1, 41),
                               atol=1e-12)
    # ITU-R BT.2408: HDR reference white 203 cd/m2 sits at 75 % HLG signal
    assert oetf_HLG(hlg_reference_E(203.0)) == pytest.approx(0.75, abs=0.002)


def test_hdr_encode_codes():
    from nrhdr_core.tonemap import hdr_encode, hlg_reference_E
    diffuse = 4094.0
    v = np.array([[-1.0, 0.0, diffuse / 2, diffuse, 4 * diffuse, 1e9, np.nan]], np.float32)
    out = hdr_encode(v, diffuse, "pq", reference_white=203.0)
    assert out.dtype == np.uint16 and (out % 64 == 0).all()
    exp = [narrow10(pq(max(x, 0.0) / diffuse * 203.0)) if np.isfinite(x) else 64 for x in v[0].astype(float)]
    assert list(out[0] >> 6) == exp
    assert exp[0] == 64 and exp[3] == 573 and exp[5] == 940       # black, 203 cd/m2, 10000 cd/m2
    e_ref = hlg_reference_E(100.0)
    out = hdr_encode(v, diffuse, "hlg", reference_white=100.0, exposure_stops=1.0)
    exp = [narrow10(hlg(max(x, 0.0) * 2 / diffuse * e_ref)) if np.isfinite(x) else 64 for x in v[0].astype(float)]
    assert list(out[0] >> 6) == exp
    with pytest.raises(ValueError, match="transfer"):
        hdr_encode(v, diffuse, "sdr")


# ---- element ---------------------------------------------------------------------------------------------

def hdr_caps(w, h, white, diffuse):
    return (f"other/x-nrhdr,layout=f32-u8-planar,width={w},height={h},framerate=5/1,white=(double){white},"
            f"diffuse-white=(double){diffuse}")


@pytest.mark.gst
@pytest.mark.parametrize("transfer,fmt", [("pq", "GRAY16_LE"), ("hlg", "GRAY16_LE"), ("pq", "GRAY16_BE")])
def test_nrtonemap_hdr_output(gst, transfer, fmt):
    from nrhdr_core.tonemap import hlg_reference_E
    h, w = 5, 30
    diffuse, white = 4094.0, 4094.0 * 6.35
    v = np.geomspace(0.5, white, h * w).astype(np.float32).reshape(h, w)
    s = np.zeros((h, w), np.uint8)
    r = run_appsrc(f"nrtonemap transfer={transfer} reference-white=300 ! video/x-raw,format={fmt}",
                   hdr_caps(w, h, white, diffuse), [hdr_buffer(v, s, pts=i, duration=1) for i in range(2)])
    assert r.error is None, r.error_text
    assert len(r.samples) == 2
    caps, _, _, img = r.samples[0]
    assert f"colorimetry=(string)bt2100-{transfer}" in caps and f"format=(string){fmt}" in caps
    if fmt == "GRAY16_BE":   # sample_payload reads native little-endian words
        img = img.byteswap()
    if transfer == "pq":
        exp = [narrow10(pq(x / diffuse * 300.0)) for x in v.ravel().astype(float)]
    else:
        exp = [narrow10(hlg(x / diffuse * hlg_reference_E(300.0))) for x in v.ravel().astype(float)]
    assert (img % 64 == 0).all()
    assert np.abs((img.ravel() >> 6).astype(int) - np.array(exp)).max() <= 1     # float32 input


@pytest.mark.gst
def test_nrtonemap_pq_negotiates_10bit_yuv_through_videoconvert(gst):
    h, w = 8, 16
    v = np.full((h, w), 4094.0, np.float32)       # diffuse white -> 203 cd/m2 -> PQ code 573
    r = run_appsrc("nrtonemap transfer=pq ! videoconvert ! video/x-raw,format=I420_10LE,colorimetry=bt2100-pq",
                   hdr_caps(w, h, 26000.0, 4094.0), [hdr_buffer(v, np.zeros((h, w), np.uint8), pts=0, duration=1)])
    assert r.error is None, r.error_text
    caps, _, _, y = r.samples[0]       # sample_payload: the Y plane (10-bit words)
    assert "I420_10LE" in caps and "colorimetry=(string)bt2100-pq" in caps
    assert (np.abs(y.astype(int) - narrow10(pq(203.0))) <= 1).all(), np.unique(y)


@pytest.mark.gst
@pytest.mark.parametrize("transfer", ["pq", "hlg"])
def test_nrtonemap_peak_rolls_off_from_the_caps_white(gst, transfer):
    """peak=1000: the caps' white (ND x the diffuse white) lands on the peak's code through the BT.2390 EETF;
    values below the knee keep their codes."""
    from nrhdr_core.tonemap import hdr_encode, peak_luminance
    h, w = 4, 50
    diffuse, white = 4094.0, 4094.0 * 6.35
    v = np.geomspace(1.0, white, h * w).astype(np.float32).reshape(h, w)
    r = run_appsrc(f"nrtonemap transfer={transfer} peak=1000 ! video/x-raw,format=GRAY16_LE",
                   hdr_caps(w, h, white, diffuse), [hdr_buffer(v, np.zeros((h, w), np.uint8), pts=0, duration=1)])
    assert r.error is None, r.error_text
    img = r.samples[0][3] >> 6
    exp = hdr_encode(v, diffuse, transfer, peak=1000.0, source_peak=peak_luminance(white, diffuse, transfer)) >> 6
    np.testing.assert_array_equal(img, exp)
    top = narrow10(pq(1000.0) - 0.5 / 876) if transfer == "pq" else 940      # the last code at or below 1000
    assert img.max() == top and img[0, 0] == narrow10(pq(1.0 / diffuse * 203.0) if transfer == "pq"
                                                      else hlg(1.0 / diffuse * hlg_E()))


def hlg_E():
    from nrhdr_core.tonemap import hlg_reference_E
    return hlg_reference_E(203.0)


@pytest.mark.gst
def test_reference_white_while_playing(gst):
    h, w = 2, 4
    v = np.full((h, w), 4094.0, np.float32)
    bufs = [hdr_buffer(v, np.zeros((h, w), np.uint8), pts=i, duration=1) for i in range(2)]

    def before(i, pipeline):
        if i == 1:
            pipeline.get_by_name("t").set_property("reference-white", 1000.0)

    r = run_appsrc("nrtonemap name=t transfer=pq ! video/x-raw,format=GRAY16_LE", hdr_caps(w, h, 26000.0, 4094.0),
                   bufs, before_push=before, lockstep=True)
    assert r.error is None, r.error_text
    assert (r.samples[0][3] >> 6 == narrow10(pq(203.0))).all()
    assert (r.samples[1][3] >> 6 == narrow10(pq(1000.0))).all()


# ---- pipelines -------------------------------------------------------------------------------------------

def run(cmd, env, timeout=180):
    p = subprocess.run([str(x) for x in cmd], env=env, capture_output=True, text=True, timeout=timeout)
    return p.returncode, p.stdout + p.stderr


@pytest.mark.gst
def test_raw_to_hdr10_png(gst_subprocess_env, tiny_clip, tmp_path):
    from nrhdr_core import io
    d, prof, raws = tiny_clip
    env = dict(gst_subprocess_env, FORMAT="png", METHOD="nearest")
    rc, out = run(["bash", ROOT / "pipelines" / "raw_to_hdr10.sh", d, tmp_path / "hdr10"], env)
    assert rc == 0, out
    files = sorted((tmp_path / "hdr10").glob("frame_*.png"))
    assert len(files) == len(raws)
    img = io.read_image(files[0], np.uint16)
    assert img.shape[:2] == (prof.height, prof.width)
    assert img.max() > img.min()
    oiio = pytest.importorskip("OpenImageIO")
    inp = oiio.ImageInput.open(str(files[0]))
    assert tuple(inp.spec().getattribute("CICP")) == (9, 16, 0, 1)       # BT.2020, PQ, RGB, full range
    inp.close()


def _x265_and_ffprobe():
    if shutil.which("ffprobe") is None or subprocess.run(["gst-inspect-1.0", "--exists", "x265enc"]).returncode:
        pytest.skip("x265enc (gstreamer1.0-plugins-bad) or ffprobe (ffmpeg) not installed")


def _signalling(path):
    p = subprocess.run(["ffprobe", "-v", "error", "-select_streams", "v:0", "-show_entries",
                        "stream=profile,color_primaries,color_transfer,color_space,color_range", "-of",
                        "default=nw=1", str(path)], capture_output=True, text=True, check=True)
    return dict(line.split("=", 1) for line in p.stdout.splitlines())


@pytest.mark.gst
@pytest.mark.parametrize("out_name,transfer,written", [("hdr10.mkv", "hlg", "hdr10.mkv"),
                                                       ("hdr10.mp4", "pq", "hdr10.mp4"),
                                                       ("hdr10", "pq", "hdr10.mkv")])
def test_raw_to_hdr10_encoded(gst_subprocess_env, tiny_clip, tmp_path, out_name, transfer, written):
    _x265_and_ffprobe()
    d, prof, raws = tiny_clip
    env = dict(gst_subprocess_env, METHOD="nearest", TRANSFER=transfer)
    rc, out = run(["bash", ROOT / "pipelines" / "raw_to_hdr10.sh", d, tmp_path / out_name], env)
    assert rc == 0, out
    assert [p.name for p in tmp_path.iterdir()] == [written]
    sig = _signalling(tmp_path / written)
    assert sig == {"profile": "Main 10", "color_primaries": "bt2020", "color_space": "bt2020nc", "color_range": "tv",
                   "color_transfer": "smpte2084" if transfer == "pq" else "arib-std-b67"}
    rc, out = run(["bash", ROOT / "pipelines" / "raw_to_hdr10.sh", d, tmp_path / out_name], env)
    assert rc == 2 and "exists" in out and "OVERWRITE=true" in out         # never overwritten unasked


@pytest.mark.gst
def test_raw_hdr_recording_pipelines(gst_subprocess_env, tiny_clip, tmp_path):
    from nrhdr_core import io
    d, prof, raws = tiny_clip
    env = dict(gst_subprocess_env, METHOD="nearest")
    rec = tmp_path / "rec" / "clip.nrhdr"
    rc, out = run(["bash", ROOT / "pipelines" / "raw_to_hdr_recording.sh", d, rec], env)
    assert rc == 0, out
    assert rec.stat().st_size == len(raws) * 5 * prof.width * prof.height
    assert "layout=(string)f32-u8-planar" in (tmp_path / "rec" / "clip.nrhdr.caps").read_text()
    rc, out = run(["bash", ROOT / "pipelines" / "hdr_recording_to_png.sh", rec, tmp_path / "png"], env)
    assert rc == 0, out
    files = sorted((tmp_path / "png").glob("frame_*.png"))
    assert len(files) == len(raws)
    assert io.read_image(files[0], np.uint8).max() > 0


@pytest.mark.gst
@pytest.mark.parametrize("transfer,mux,ext", [("pq", "mp4mux", "mp4"), ("pq", "matroskamux", "mkv"),
                                              ("hlg", "mp4mux", "mp4")])
def test_nrhdrenc_from_gst_launch(gst_subprocess_env, tiny_clip, tmp_path, transfer, mux, ext):
    """nrhdrenc in a gst-launch pipeline: the decoded codes are nrtonemap's (lossless x265), the signalling and
    the estimated metadata are in the stream and, with matroska=true, the same in the Matroska container."""
    import json
    from fractions import Fraction
    from nrhdr_core import chain, tonemap
    _x265_and_ffprobe()
    d, prof, raws = tiny_clip
    out = tmp_path / f"e.{ext}"
    opt = ["matroska=true"] if mux == "matroskamux" else []
    rc, text = run(["gst-launch-1.0", "-e", "filesrc", f"location={d / 'clip.raw'}", "!", "rawvideoparse",
                    "format=gray16-le", f"width={prof.width}", f"height={prof.height}", "framerate=5/1", "!",
                    "nrvalidity", f"profile={d / 'camera.json'}", "!", "nrcrosstalk", "mode=lut", "!",
                    "nrreconstruct", "method=nearest", "!", "nrhdrenc", f"transfer={transfer}",
                    "x265-options=lossless=1", *opt, "!", mux, "!", "filesink", f"location={out}"],
                   gst_subprocess_env)
    assert rc == 0, text
    raw = subprocess.run(["ffmpeg", "-v", "error", "-i", str(out), "-f", "rawvideo", "-pix_fmt", "yuv420p10le",
                          "-"], capture_output=True, check=True).stdout
    w, h = prof.width, prof.height
    frames = np.frombuffer(raw, "<u2").reshape(len(raws), -1)[:, :w * h].reshape(-1, h, w)
    diffuse, white = float(prof.regular_white), float(prof.white)
    for i, r in enumerate(raws):
        v, _ = chain.process_frame(r.copy(), prof, chain.ChainSettings(method="nearest", crosstalk="lut"))
        exp = tonemap.hdr_encode(v, diffuse, transfer, peak=1000.0,
                                 source_peak=tonemap.peak_luminance(white, diffuse, transfer)) >> 6
        np.testing.assert_array_equal(frames[i], exp)
    sig = _signalling(out)
    assert sig["color_transfer"] == ("smpte2084" if transfer == "pq" else "arib-std-b67")
    assert (sig["color_primaries"], sig["color_space"], sig["color_range"]) == ("bt2020", "bt2020nc", "tv")
    p = subprocess.run(["ffprobe", "-v", "error", "-select_streams", "v:0", "-read_intervals", "%+#1", "-show_frames",
                        "-show_streams", "-of", "json", str(out)], capture_output=True, text=True, check=True)
    info = json.loads(p.stdout)
    places = [info["frames"][0]] + ([info["streams"][0]] if ext == "mkv" else [])
    for where in places:
        kinds = {x["side_data_type"]: x for x in where.get("side_data_list", [])}
        if transfer == "hlg":
            assert "Mastering display metadata" not in kinds
            continue
        md = kinds["Mastering display metadata"]
        assert Fraction(md["max_luminance"]) == 1000 and Fraction(md["min_luminance"]) == Fraction(1, 200)
        cll = kinds["Content light level metadata"]
        assert (cll["max_content"], cll["max_average"]) == (1000, 203)    # the estimate: peak, reference white


@pytest.mark.gst
def test_frames_narrower_than_a_coding_tree_unit_are_refused(gst_subprocess_env, tmp_path):
    """x265enc aborts the process on some frames narrower than 64 pixels (48 x 32: `free(): invalid next
    size`): nrhdrenc posts an error naming itself and the size instead, and `nrhdr hdr10` refuses such a clip
    before its first frame, leaving nothing behind; 64 pixels wide encodes."""
    from conftest import make_test_clip
    _x265_and_ffprobe()
    d, prof, raws = make_test_clip(tmp_path / "narrow", width=48, height=32, frames=2)
    out = tmp_path / "e.mp4"
    rc, text = run(["gst-launch-1.0", "-e", "filesrc", f"location={d / 'clip.raw'}", "!", "rawvideoparse",
                    "format=gray16-le", "width=48", "height=32", "framerate=5/1", "!", "nrvalidity",
                    f"profile={d / 'camera.json'}", "!", "nrreconstruct", "method=nearest", "!", "nrhdrenc", "!",
                    "mp4mux", "!", "filesink", f"location={out}"], gst_subprocess_env)
    assert rc != 0 and "nrhdrenc" in text and "48x32 frames are narrower than 64 pixels" in text, text
    assert "invalid next size" not in text and "Aborted" not in text, text
    v = tmp_path / "v.mp4"
    rc, text = run([gst_subprocess_env["NRHDR"], "hdr10", d, v, "--method", "nearest", "--no-progress"],
                   gst_subprocess_env)
    assert rc == 2 and "48x32 frames are narrower than 64 pixels" in text, text
    assert not [x.name for x in tmp_path.iterdir() if x.name.startswith("v.") or x.name.startswith(".v")]
