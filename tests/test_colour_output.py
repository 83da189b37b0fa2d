"""Colour output (docs/COLOUR.md "Colour output", docs/TONEMAP.md, docs/HDR-OUTPUT.md): the hue-keeping tone map,
grey-world white balance, BT.709 -> BT.2020 and PQ / HLG in colour, Y'CbCr for HEVC, the elements and the
colour EXR, against expectations computed here (sRGB, ST 2084 and the primaries' matrix written out in the
test)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from nrhdr_core import hdr_output, tonemap

H, W = 24, 32


# ---- independent references -------------------------------------------------------------------------------
def srgb_decode(code8):
    """IEC 61966-2-1: 8-bit code -> linear light."""
    v = np.asarray(code8, np.float64) / 255.0
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def pq_signal(nits):
    """SMPTE ST 2084 inverse EOTF, constants as published."""
    m1, m2 = 2610 / 16384, 2523 / 4096 * 128
    c1, c2, c3 = 3424 / 4096, 2413 / 4096 * 32, 2392 / 4096 * 32
    y = np.clip(np.asarray(nits, np.float64) / 10000.0, 0, 1) ** m1
    return ((c1 + c2 * y) / (1 + c3 * y)) ** m2


def code10(signal):
    return np.floor(64 + 876 * np.asarray(signal) + 0.5).astype(int)


def npm(primaries, white=(0.3127, 0.3290)):
    """RGB -> XYZ from the chromaticities (SMPTE RP 177 section 3.3), written out."""
    (xr, yr), (xg, yg), (xb, yb) = primaries
    cols = np.array([[x / y, 1.0, (1 - x - y) / y] for x, y in ((xr, yr), (xg, yg), (xb, yb))]).T
    xw, yw = white
    wxyz = np.array([xw / yw, 1.0, (1 - xw - yw) / yw])
    s = np.linalg.inv(cols) @ wxyz
    return cols * s


BT709 = ((0.64, 0.33), (0.30, 0.60), (0.15, 0.06))
BT2020 = ((0.708, 0.292), (0.170, 0.797), (0.131, 0.046))


def ramp(lo=1.0, hi=2e4):
    return np.geomspace(lo, hi, H * W).astype(np.float32).reshape(H, W)


# ---- SDR tone map -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("operator", tonemap.SDR_OPERATORS)
def test_grey_stays_grey_and_matches_monochrome(operator):
    g = ramp()
    out = tonemap.tonemap_rgb(np.stack([g, g, g]), 2e4, operator)
    assert out.shape == (H, W, 3) and out.dtype == np.uint8
    assert (out[..., 0] == out[..., 1]).all() and (out[..., 1] == out[..., 2]).all()
    mono = tonemap.log_tonemap(g, 2e4) if operator == "log" else tonemap.local_tonemap(g, 2e4)
    assert np.abs(out[..., 1].astype(int) - mono).max() <= 1


@pytest.mark.parametrize("operator", tonemap.SDR_OPERATORS)
def test_hue_and_saturation_kept_in_gamut(operator):
    """In-gamut colours: the displayed linear channels keep the scene's channel ratios (within the 8-bit
    quantisation), and the displayed luminance is the grey tone map's."""
    g = ramp(10.0, 2e3)
    ratio = np.array([1.0, 0.55, 0.3])
    rgb = (g[None] * ratio[:, None, None]).astype(np.float32)
    out = tonemap.tonemap_rgb(rgb, 2e4, operator)
    lin = srgb_decode(out)
    ok = out[..., 2] >= 40                   # quantisation of a dark channel would dominate
    assert ok.sum() > 100
    got = lin[ok] / lin[ok][:, :1]
    assert np.allclose(got[:, 1], 0.55, rtol=0.03) and np.allclose(got[:, 2], 0.3, rtol=0.05)


def test_saturation_exponent():
    g = ramp(10.0, 2e3)
    rgb = np.stack([g, 0.5 * g, 0.25 * g]).astype(np.float32)
    out = tonemap.tonemap_rgb(rgb, 2e4, "log", saturation=0.5)
    lin = srgb_decode(out)
    ok = (out[..., 2] >= 60) & (out[..., 0] < 255)        # half a code: < 2 % of the light; not out of gamut
    assert ok.sum() > 100
    assert np.allclose(lin[ok][:, 1] / lin[ok][:, 0], 0.5 ** 0.5, rtol=0.04)
    assert np.allclose(lin[ok][:, 2] / lin[ok][:, 0], 0.25 ** 0.5, rtol=0.04)


def test_out_of_gamut_keeps_hue_and_luminance():
    """A saturated colour brighter than the display can show: mixed with its grey, never clipped per channel:
    the largest channel at full scale, the channel differences keep their proportions (hue), the luminance is
    the grey tone map's."""
    v = np.full((H, W), 1e4, np.float32)
    rgb = np.stack([v, 0.2 * v, 0.05 * v])
    out = tonemap.tonemap_rgb(rgb, 1e4, "log")
    lin = srgb_decode(out[0, 0])
    assert out[0, 0, 0] == 255 and out[0, 0, 2] > 0
    lum = tonemap.LUMA_BT709[0] * rgb[0] + (1 - sum(tonemap.LUMA_BT709)) * rgb[1] + tonemap.LUMA_BT709[1] * rgb[2]
    y = srgb_decode(tonemap.log_tonemap(lum.astype(np.float32), 1e4)[0, 0])
    got = 0.2126 * lin[0] + 0.7152 * lin[1] + 0.0722 * lin[2]
    assert abs(got - y) < 0.02
    assert abs((lin[0] - lin[1]) / (lin[0] - lin[2]) - (1 - 0.2) / (1 - 0.05)) < 0.03


def test_white_balance_gains_and_bad_input():
    g = ramp()
    tinted = np.stack([1.25 * g, g, 0.8 * g]).astype(np.float32)
    out = tonemap.tonemap_rgb(tinted, 2e4, "log", white_balance=(0.8, 1.0, 1.25))
    assert np.abs(out[..., 0].astype(int) - out[..., 1]).max() <= 1
    assert np.abs(out[..., 2].astype(int) - out[..., 1]).max() <= 1
    with pytest.raises(ValueError, match="white balance"):
        tonemap.tonemap_rgb(tinted, 2e4, "log", white_balance=(1, 0, 1))
    with pytest.raises(ValueError, match=r"\(3, H, W\)"):
        tonemap.tonemap_rgb(g, 2e4, "log")
    nasty = tinted.copy()
    nasty[0, 0, 0], nasty[1, 0, 1], nasty[2, 0, 2] = np.nan, np.inf, -5.0
    out = tonemap.tonemap_rgb(nasty, 2e4, "local")
    assert out.dtype == np.uint8


def test_local_rgb_statistics_follow_the_luminance():
    """LocalTonemap.rgb keeps the operator's temporal statistics: the same parameters as the grey operator
    given the luminance."""
    g = ramp()
    rgb = np.stack([g, 0.7 * g, 0.4 * g]).astype(np.float32)
    lum = (0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]).astype(np.float32)
    a, b = tonemap.LocalTonemap(0.5), tonemap.LocalTonemap(0.5)
    for k in (1.0, 4.0):
        a.rgb(rgb * np.float32(k), 2e4)
        b(lum * np.float32(k), 2e4)
        assert np.allclose(a.params, b.params, rtol=1e-4, atol=1e-5)


def test_grey_world_on_a_tinted_grey_scene():
    rng = np.random.default_rng(1)
    grey = rng.uniform(50, 3000, (H * 4, W * 4)).astype(np.float32)
    tint = np.array([1.3, 1.0, 0.6], np.float32)
    rgb = grey[None] * tint[:, None, None]
    rgb[:, :8, :] = 4000.0                    # clipped: grey at the top, whatever the light's colour
    rgb[:, 8:16, :] *= 1e-5                   # near black: noise
    gains = tonemap.grey_world(rgb, white=4000.0)
    assert np.allclose(gains, 1 / tint, rtol=0.01)
    assert tonemap.grey_world(np.zeros((3, 8, 8), np.float32)) == (1.0, 1.0, 1.0)
    gw = tonemap.GreyWorld(speed=1.0, white=4000.0)
    assert np.allclose(gw.update(rgb), 1 / tint, rtol=0.01)


# ---- HDR ---------------------------------------------------------------------------------------------------
def test_bt709_to_bt2020_matrix_from_the_primaries():
    m = np.linalg.inv(npm(BT2020)) @ npm(BT709)
    assert np.allclose(tonemap.primaries_matrix("bt709", "bt2020"), m, atol=1e-12)
    bt2087 = [[0.6274, 0.3293, 0.0433], [0.0691, 0.9195, 0.0114], [0.0164, 0.0880, 0.8956]]
    assert np.allclose(m, bt2087, atol=1e-4)
    # the encoder: a pure BT.709 red / green / blue patch at the diffuse white -> the matrix's column in PQ
    dw = 1000.0
    for k in range(3):
        rgb = np.zeros((3, 4, 4), np.float32)
        rgb[k] = dw
        codes = tonemap.hdr_encode_rgb(rgb, dw, "pq") >> 6
        want = code10(pq_signal(m[:, k] * 203.0))
        assert (codes[:, 0, 0] == want).all(), (k, codes[:, 0, 0], want)
    same = tonemap.hdr_encode_rgb(rgb, dw, "pq", primaries="bt709") >> 6
    assert (same[:, 0, 0] == code10(pq_signal(np.array([0.0, 0.0, 203.0])))).all()


def test_pq_of_known_values():
    """ST 2084: 100 cd/m2 -> 0.5081, 1000 -> 0.7518, 10000 -> 1 (10-bit narrow 509, 723, 940); 0 -> 64."""
    dw = 203.0     # value = cd/m2 at the default reference white
    rgb = np.zeros((3, 1, 4), np.float32)
    rgb[:, 0] = np.array([0.0, 100.0, 1000.0, 10000.0], np.float32)
    codes = tonemap.hdr_encode_rgb(rgb, dw, "pq") >> 6
    assert (codes == np.array([64, 509, 723, 940])).all()
    assert abs(float(pq_signal(100)) - 0.5081) < 1e-4 and abs(float(pq_signal(1000)) - 0.7518) < 1e-4


@pytest.mark.parametrize("transfer", tonemap.TRANSFERS)
@pytest.mark.parametrize("peak", [0.0, 1000.0])
def test_grey_hdr_equals_monochrome(transfer, peak):
    g = ramp(1e-3, 2e4)
    g[0, :3] = 0.0, -1.0, np.nan
    src = tonemap.peak_luminance(2e4, 1000.0, transfer) if peak else 0.0
    c = tonemap.hdr_encode_rgb(np.stack([g, g, g]), 1000.0, transfer, peak=peak, source_peak=src)
    m = tonemap.hdr_encode(g, 1000.0, transfer, peak=peak, source_peak=src)
    assert (c == m[None]).all()


def test_hdr_roll_off_keeps_hue():
    """With the BT.2390 roll-off, a colour's largest channel gets the EETF's light and the others keep their
    ratio to it (linear BT.2020 light)."""
    v = np.full((2, 2), 4000.0, np.float32)
    rgb = np.stack([v, 0.5 * v, 0.25 * v])
    src = tonemap.peak_luminance(6350.0, 1000.0)
    codes = (tonemap.hdr_encode_rgb(rgb, 1000.0, "pq", primaries="bt709", peak=1000, source_peak=src) >> 6)[:, 0, 0]
    light = np.array([tonemap.eotf_ST2084((c - 64) / 876) for c in codes])
    want_top = tonemap.eetf_BT2390(4000 / 1000 * 203, src, 1000)
    assert abs(light[0] - want_top) / want_top < 0.01
    assert np.allclose(light[1:] / light[0], [0.5, 0.25], rtol=0.02)


def test_light_levels_in_colour():
    """CTA-861.3: a pixel's light is max(R, G, B)."""
    codes = np.zeros((3, 2, 2), np.uint16)
    codes[:] = 64 << 6
    codes[2, 0, 0] = 723 << 6           # a blue pixel at about 1000 cd/m2
    ll = hdr_output.LightLevels("pq")
    ll.update(codes)
    nits = tonemap.eotf_ST2084((723 - 64) / 876)
    assert ll.max_cll == int(np.ceil(nits - 1e-9))
    assert ll.max_fall_int == int(np.ceil(nits / 4 - 1e-9))


def ycbcr_back(y, cb, cr):
    """BT.2020 NCL Y'CbCr (10-bit narrow) -> R'G'B' signal, inverted here."""
    kr, kb = 0.2627, 0.0593
    yp, pb, pr = (y - 64) / 876, (cb - 512) / 896, (cr - 512) / 896
    r = yp + (2 - 2 * kr) * pr
    b = yp + (2 - 2 * kb) * pb
    g = (yp - kr * r - kb * b) / (1 - kr - kb)
    return np.stack([r, g, b])


@pytest.mark.parametrize("subsample", [False, True])
def test_ycbcr_frame_bt2020_ncl(subsample):
    h, w = 6, 8
    rgb = np.zeros((3, h, w), np.float32)
    rgb[:, :, :4] = 500.0                                   # grey left half
    rgb[:, :, 4:] = np.array([800.0, 300.0, 100.0], np.float32)[:, None, None]    # a colour right half
    codes = tonemap.hdr_encode_rgb(rgb, 1000.0, "pq")
    ch, cw = ((h + 1) // 2, (w + 1) // 2) if subsample else (h, w)
    sizes = [h * w * 2, ch * cw * 2, ch * cw * 2]
    offsets = [0, sizes[0], sizes[0] + sizes[1]]
    strides = [w * 2, cw * 2, cw * 2]
    frame = np.zeros(sum(sizes), np.uint8)
    hdr_output.ycbcr_frame(codes, frame, offsets, strides, subsample=subsample)
    y = frame[:sizes[0]].view("<u2").reshape(h, w).astype(float)
    cb = frame[offsets[1]:offsets[2]].view("<u2").reshape(ch, cw).astype(float)
    cr = frame[offsets[2]:].view("<u2").reshape(ch, cw).astype(float)
    assert (y[:, :4] == codes[1, :, :4] >> 6).all()                         # grey: Y' is the code
    grey_c = (slice(None), slice(0, 1)) if subsample else (slice(None), slice(0, 4))
    assert (cb[grey_c] == 512).all() and (cr[grey_c] == 512).all()
    cx = 3 if subsample else 6                                               # inside the colour half
    back = ycbcr_back(y[0, 6], cb[0, cx], cr[0, cx])
    assert np.abs(64 + 876 * back - (codes[:, 0, 6] >> 6)).max() <= 1.0


# ---- elements ----------------------------------------------------------------------------------------------
FPS, DUR = 10, 100_000_000


def colour_caps(w, h, white=None, diffuse=None, profile=None):
    c = f"other/x-nrhdr,layout=(string)rgb-f32-u8-planar,width={w},height={h},framerate={FPS}/1"
    if white is not None:
        c += f",white=(double){white}"
    if diffuse is not None:
        c += f",diffuse-white=(double){diffuse}"
    if profile is not None:
        c += f",profile=(string)\"{profile}\""
    return c


def colour_buffer(rgb, state, i):
    """The rgb-f32-u8-planar layout written out here: float32 R, G, B planes then the uint8 state plane."""
    from gi.repository import Gst
    buf = Gst.Buffer.new_wrapped(np.ascontiguousarray(rgb, "<f4").tobytes() + np.ascontiguousarray(state, np.uint8).tobytes())
    buf.pts, buf.duration = i * DUR, DUR
    return buf


def run_frames(desc, caps, buffers):
    """appsrc ! desc ! appsink: [(caps string, bytes of each frame)] and the first error."""
    from gi.repository import Gst, GstApp  # noqa: F401
    pipeline = Gst.parse_launch(f"appsrc name=src format=time ! {desc} ! appsink name=sink sync=false")
    src, sink = pipeline.get_by_name("src"), pipeline.get_by_name("sink")
    src.set_property("caps", Gst.Caps.from_string(caps))
    out, error = [], None
    bus = pipeline.get_bus()
    try:
        pipeline.set_state(Gst.State.PLAYING)
        for b in buffers:
            src.push_buffer(b)
        src.end_of_stream()
        while True:
            m = bus.pop_filtered(Gst.MessageType.ERROR)
            if m is not None:
                error = f"{m.src.get_name()}: {m.parse_error()[0].message}"
                break
            smp = sink.try_pull_sample(120 * Gst.SECOND)   # None at EOS
            if smp is None:
                m = bus.pop_filtered(Gst.MessageType.ERROR)
                if m is not None:
                    error = f"{m.src.get_name()}: {m.parse_error()[0].message}"
                break
            buf = smp.get_buffer()
            ok, mi = buf.map(Gst.MapFlags.READ)
            out.append((smp.get_caps().to_string(), bytes(mi.data)))
            buf.unmap(mi)
    finally:
        pipeline.set_state(Gst.State.NULL)
    return out, error


def run_to_eos(desc, caps, buffers):
    """appsrc (caps) ! desc (ending in a sink): push `buffers`, EOS, wait for it; an error fails the test."""
    from gi.repository import Gst
    pipeline = Gst.parse_launch(f"appsrc name=src format=time caps=\"{caps}\" ! {desc}")
    src = pipeline.get_by_name("src")
    try:
        pipeline.set_state(Gst.State.PLAYING)
        for b in buffers:
            src.push_buffer(b)
        src.end_of_stream()
        m = pipeline.get_bus().timed_pop_filtered(120 * Gst.SECOND, Gst.MessageType.ERROR | Gst.MessageType.EOS)
        assert m is not None and m.type == Gst.MessageType.EOS, m and "{}: {} ({})".format(
            m.src.get_name(), m.parse_error()[0].message, m.parse_error()[1])   # debug text: which check failed
    finally:
        pipeline.set_state(Gst.State.NULL)


def rgb_scene(h=H, w=W, seed=3):
    rng = np.random.default_rng(seed)
    g = ramp(5.0, 3e4)[:h, :w]
    tint = rng.uniform(0.2, 1.0, (3, h, w)).astype(np.float32)
    rgb = (g[None] * tint).astype(np.float32)
    rgb[:, :2, :2] = 800.0                   # a grey patch
    return rgb


@pytest.mark.parametrize("operator", tonemap.SDR_OPERATORS)
def test_nrtonemap_colour_equals_core(gst, operator):
    """Colour frames to RGB: the element's bytes are tonemap_rgb's (the local operator's statistics smoothed
    over the frames as LocalTonemap.rgb does), rows padded to 4 bytes (w = 30: 90-byte rows, stride 92)."""
    h, w = 10, 30
    frames = [rgb_scene(h, w) * np.float32(k) for k in (1.0, 2.0, 0.5)]
    state = np.zeros((h, w), np.uint8)
    white = 4094 * 6.35
    out, err = run_frames(f"nrtonemap operator={operator} white-balance=none smoothing=0.5 ! video/x-raw,format=RGB",
                          colour_caps(w, h, white), [colour_buffer(f, state, i) for i, f in enumerate(frames)])
    assert err is None, err
    assert len(out) == 3 and "format=(string)RGB" in out[0][0]
    local = tonemap.LocalTonemap(0.5)
    for f, (_, data) in zip(frames, out):
        want = local.rgb(f, white) if operator == "local" else tonemap.tonemap_rgb(f, white, "log")
        got = np.ndarray((h, w, 3), np.uint8, data, 0, (92, 3, 1))
        assert (got == want).all()
        assert got[0, 0, 0] == got[0, 0, 1] == got[0, 0, 2]


def test_nrtonemap_white_balance_from_profile_and_grey_world(gst, tmp_path):
    from nrhdr_core import profile
    h, w = 8, 12
    prof = profile.default(h, w, cfa="rggb")
    prof = dataclasses.replace(prof, white_balance=(0.5, 1.0, 2.0))
    path = tmp_path / "camera.json"
    profile.save(prof, path)
    grey = ramp(50.0, 3000.0)[:h, :w]
    tinted = np.stack([2.0 * grey, grey, 0.5 * grey]).astype(np.float32)
    state = np.zeros((h, w), np.uint8)
    for wb in ("profile", "grey-world"):
        out, err = run_frames(f"nrtonemap operator=log white-balance={wb} ! video/x-raw,format=RGB",
                              colour_caps(w, h, 26000.0, profile=path), [colour_buffer(tinted, state, 0)])
        assert err is None, err
        img = np.ndarray((h, w, 3), np.uint8, out[0][1], 0, (w * 3, 3, 1)).astype(int)
        assert np.abs(img[..., 0] - img[..., 1]).max() <= 1 and np.abs(img[..., 2] - img[..., 1]).max() <= 1, wb
    out, err = run_frames("nrtonemap operator=log white-balance=profile ! video/x-raw,format=RGB",
                          colour_caps(w, h, 26000.0), [colour_buffer(tinted, state, 0)])
    assert err is None, err                   # no profile in the caps: no gains
    img = np.ndarray((h, w, 3), np.uint8, out[0][1], 0, (w * 3, 3, 1)).astype(int)
    assert (img[..., 0] >= img[..., 1]).all() and (img[..., 0] > img[..., 1]).any()


@pytest.mark.parametrize("fmt,transfer", [("I420_10LE", "pq"), ("Y444_10LE", "pq"), ("I420_10LE", "hlg")])
def test_nrtonemap_colour_hdr_equals_core(gst, fmt, transfer):
    h, w = 6, 10
    rgb = rgb_scene(h, w)
    state = np.zeros((h, w), np.uint8)
    white, diffuse = 4094 * 6.35, 4094.0
    out, err = run_frames(f"nrtonemap transfer={transfer} peak=1000 white-balance=none ! video/x-raw,format={fmt}",
                          colour_caps(w, h, white, diffuse), [colour_buffer(rgb, state, 0)])
    assert err is None, err
    assert f"colorimetry=(string)bt2100-{transfer}" in out[0][0]
    src = tonemap.peak_luminance(white, diffuse, transfer)
    codes = tonemap.hdr_encode_rgb(rgb, diffuse, transfer, peak=1000, source_peak=src)
    from gi.repository import Gst, GstVideo
    vi = GstVideo.VideoInfo.new_from_caps(Gst.Caps.from_string(out[0][0]))
    want = np.zeros(vi.size, np.uint8)
    hdr_output.ycbcr_frame(codes, want, vi.offset, vi.stride, subsample=fmt == "I420_10LE")
    ch, cw = ((h + 1) // 2, (w + 1) // 2) if fmt == "I420_10LE" else (h, w)
    for k, (ph, pw) in enumerate(((h, w), (ch, cw), (ch, cw))):      # the planes, not the rows' padding
        got_plane = np.ndarray((ph, pw), "<u2", out[0][1], vi.offset[k], (vi.stride[k], 2))
        want_plane = np.ndarray((ph, pw), "<u2", want, vi.offset[k], (vi.stride[k], 2))
        assert (got_plane == want_plane).all(), k
    y = np.ndarray((h, w), "<u2", out[0][1], vi.offset[0], (vi.stride[0], 2))
    assert y[0, 0] == codes[1, 0, 0] >> 6            # the grey patch: Y' = its code


def test_nrexrsink_colour_round_trip(gst, tmp_path):
    """Colour frames recorded as EXR channels R, G, B (+ state) and read back exactly."""
    import OpenImageIO as oiio
    from nrhdr_core import io
    h, w = 6, 9
    frames = [rgb_scene(h, w, seed=k) for k in range(2)]
    frames[1][0, 0, 0] = 1e9
    states = [np.full((h, w), k * 0x40, np.uint8) for k in range(2)]
    run_to_eos(f"nrexrsink location={tmp_path}/f_%02d.exr write-state=true", colour_caps(w, h, 26000.0),
               [colour_buffer(f, s, i) for i, (f, s) in enumerate(zip(frames, states))])
    for i, (f, s) in enumerate(zip(frames, states)):
        path = tmp_path / f"f_{i:02d}.exr"
        inp = oiio.ImageInput.open(str(path))
        names = list(inp.spec().channelnames)
        inp.close()
        assert sorted(names) == ["B", "G", "R", "state"] and io.exr_channels(path) == 3
        v, st = io.read_exr(path)
        assert v.shape == (3, h, w) and (v == f).all() and (st == s).all()


def patches(h=32, w=64):
    """Flat 16 x 16 patches (linear camera RGB, diffuse white 4094): grey, orange, green, blue, at
    several levels."""
    cols = [(1.0, 1.0, 1.0), (1.0, 0.45, 0.1), (0.2, 0.9, 0.3), (0.15, 0.25, 1.0)]
    rgb = np.zeros((3, h, w), np.float32)
    for j, c in enumerate(cols):
        for i, level in enumerate((800.0, 3000.0)):
            rgb[:, i * 16:(i + 1) * 16, j * 16:(j + 1) * 16] = np.array(c, np.float32)[:, None, None] * level
    return rgb


@pytest.mark.gst
def test_nrhdrenc_colour_decoded_by_ffmpeg(gst, tmp_path):
    """HDR10 in colour through nrhdrenc (lossless x265), decoded by ffmpeg: BT.2020 / PQ / BT.2020 NCL in the
    stream; the decoded Y'CbCr equals ycbcr_frame's; ffmpeg's own conversion back to R'G'B' gives each patch's
    PQ codes (BT.709 -> BT.2020, from hdr_encode_rgb) within the Y'CbCr rounding (1.5 codes), and grey stays
    grey."""
    import json
    import shutil
    import subprocess
    if shutil.which("ffmpeg") is None or gst.ElementFactory.find("x265enc") is None:
        pytest.skip("needs x265enc and ffmpeg")
    h, w = 32, 64
    rgb = patches(h, w)
    state = np.zeros((h, w), np.uint8)
    white, diffuse = 4094 * 6.35, 4094.0
    out = tmp_path / "c.mp4"
    run_to_eos(f"nrhdrenc white-balance=none x265-options=lossless=1 ! mp4mux ! filesink location={out}",
               colour_caps(w, h, white, diffuse), [colour_buffer(rgb, state, i) for i in range(2)])
    p = subprocess.run(["ffprobe", "-v", "error", "-select_streams", "v:0", "-show_entries",
                        "stream=profile,pix_fmt,color_primaries,color_transfer,color_space,color_range", "-of", "json",
                        str(out)], capture_output=True, text=True, check=True)
    st = json.loads(p.stdout)["streams"][0]
    assert (st["profile"], st["pix_fmt"], st["color_primaries"], st["color_transfer"], st["color_space"],
            st["color_range"]) == ("Main 10", "yuv420p10le", "bt2020", "smpte2084", "bt2020nc", "tv")
    codes = tonemap.hdr_encode_rgb(rgb, diffuse, "pq", peak=1000.0,
                                   source_peak=tonemap.peak_luminance(white, diffuse))
    yuv = subprocess.run(["ffmpeg", "-v", "error", "-i", str(out), "-frames:v", "1", "-f", "rawvideo", "-pix_fmt",
                          "yuv420p10le", "-"], capture_output=True, check=True).stdout
    want = np.zeros(w * h * 2 * 3 // 2, np.uint8)
    hdr_output.ycbcr_frame(codes, want, (0, w * h * 2, w * h * 2 * 5 // 4), (w * 2, w, w))
    assert yuv == want.tobytes()
    # ffmpeg's conversion (its BT.2020 NCL matrix, limited to full range) back to R'G'B', 16-bit
    rgb16 = subprocess.run(["ffmpeg", "-v", "error", "-i", str(out), "-frames:v", "1", "-vf",
                            "scale=in_color_matrix=bt2020:in_range=limited:out_range=full:flags=accurate_rnd+full_chroma_int",
                            "-pix_fmt", "gbrp16le", "-f", "rawvideo", "-"], capture_output=True, check=True).stdout
    g_, b_, r_ = np.frombuffer(rgb16, "<u2").reshape(3, h, w).astype(float)
    dec = np.stack([r_, g_, b_]) / 65535 * 876 + 64               # back to 10-bit narrow-range code units
    # swscale's limited -> full range scaling is off by about 255/256: calibrated on the two grey patches
    # (R' = G' = B'), so that what is checked is the colour conversion
    grey_dec = np.array([dec[1, 8, 8], dec[1, 24, 8]])
    grey_want = np.array([codes[1, 8, 8], codes[1, 24, 8]], float) / 64
    a, b = np.polyfit(grey_want, grey_dec, 1)
    assert abs(a - 1) < 0.01
    dec = (dec - b) / a
    for i in range(2):
        for j in range(4):
            y0, x0 = i * 16 + 8, j * 16 + 8                       # the patch centre: flat chroma around it
            want_codes = codes[:, y0, x0] >> 6
            # Y', Cb, Cr each rounded to 10 bits: B' = Y' + 1.8814 Cb is within 0.5 + 0.94 x 876 / 896 codes
            assert np.abs(dec[:, y0, x0] - want_codes).max() <= 1.5, (i, j, dec[:, y0, x0], want_codes)
            if j == 0:
                assert np.ptp(dec[:, y0, x0]) <= 0.5                # grey stays grey
    # the BT.709 -> BT.2020 conversion happened: the orange patch is less saturated in BT.2020 codes than
    # the same light would be in BT.709
    bt709 = tonemap.hdr_encode_rgb(rgb, diffuse, "pq", primaries="bt709", peak=1000.0,
                                   source_peak=tonemap.peak_luminance(white, diffuse)) >> 6
    assert (codes[2, 8, 24] >> 6) > bt709[2, 8, 24]


@pytest.mark.gst
def test_hdr10_cli_colour_clip(gst_subprocess_env, tmp_path):
    """`nrhdr hdr10` on a simulated colour clip: HEVC Main 10 with BT.2020 / PQ / BT.2020 NCL, the decoded
    Y'CbCr (lossless) is the colour chain's R'G'B' codes in BT.2020 NCL, MaxCLL is max(R, G, B) through the
    ST 2084 EOTF (written out here), and the stills are RGB PNG."""
    import json
    import shutil
    import subprocess
    import sys
    from nrhdr_core import batch, chain, profile
    if shutil.which("ffprobe") is None or subprocess.run(["gst-inspect-1.0", "--exists", "x265enc"]).returncode:
        pytest.skip("x265enc or ffprobe not installed")
    h, w, n = 32, 64, 2          # 64 wide: x265enc's narrowest (hdr_output.check_encode_size)
    clip = tmp_path / "clip"

    def cli(*args):
        p = subprocess.run([sys.executable, "-m", "gst_plugins.cli", *map(str, args)], env=gst_subprocess_env,
                           capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, p.stdout + p.stderr
        return p.stdout
    cli("simulate", "synthetic", "-o", clip, "--cfa", "rggb", "--frames", n, "--width", w, "--height", h)
    out = tmp_path / "c.mp4"
    cli("hdr10", clip, out, "--method", "preview", "--no-progress", "--white-balance", "none",
        "--x265-options", "lossless=1")
    p = subprocess.run(["ffprobe", "-v", "error", "-select_streams", "v:0", "-read_intervals", "%+#1",
                        "-show_frames", "-show_streams", "-of", "json", str(out)], capture_output=True, text=True,
                       check=True)
    info = json.loads(p.stdout)
    st = info["streams"][0]
    assert (st["color_primaries"], st["color_transfer"], st["color_space"]) == ("bt2020", "smpte2084", "bt2020nc")
    prof = profile.load(clip / "camera.json")
    src = batch.open_source(clip)
    diffuse, white = float(prof.regular_white), float(prof.white)
    yuv = subprocess.run(["ffmpeg", "-v", "error", "-i", str(out), "-f", "rawvideo", "-pix_fmt", "yuv420p10le", "-"],
                         capture_output=True, check=True).stdout
    per = w * h * 3 // 2 * 2
    top = 0
    for i in range(n):
        rgb, _ = chain.process_frame(batch.read_frame(src.raw, w, h, i), prof,
                                     chain.ChainSettings(method="preview", crosstalk="kernel"))
        codes = tonemap.hdr_encode_rgb(rgb, diffuse, "pq", peak=1000.0, source_peak=tonemap.peak_luminance(white, diffuse))
        want = np.zeros(per, np.uint8)
        hdr_output.ycbcr_frame(codes, want, (0, w * h * 2, w * h * 5 // 2), (w * 2, w, w))
        assert yuv[i * per:(i + 1) * per] == want.tobytes()
        top = max(top, int((codes >> 6).max()))
    cll = {x["side_data_type"]: x for x in info["frames"][0]["side_data_list"]}["Content light level metadata"]
    pq_sig = (top - 64) / 876
    m1, m2, c1, c2, c3 = 2610 / 16384, 2523 / 32, 3424 / 4096, 2413 / 128, 2392 / 128
    vp = pq_sig ** (1 / m2)
    assert cll["max_content"] == int(np.ceil(10000 * (max(vp - c1, 0) / (c2 - c3 * vp)) ** (1 / m1) - 1e-9))
    stills = tmp_path / "stills"
    cli("hdr10", clip, stills, "--method", "preview", "--no-progress")
    import OpenImageIO as oiio
    inp = oiio.ImageInput.open(str(stills / "frame_00000.png"))
    spec = inp.spec()
    inp.close()
    assert spec.nchannels == 3 and list(spec.getattribute("CICP")) == [9, 16, 0, 1]


@pytest.mark.gst
def test_colour_chain_through_the_elements(gst, tmp_path):
    """A Bayer clip through nrvalidity ! nrreconstruct ! nrtonemap: RGB equal to chain.process_frame then
    LocalTonemap.rgb with the profile's white and white balance (the stream's statistics)."""
    import dataclasses as dc
    import subprocess
    import sys
    from nrhdr_core import batch, chain, profile
    h, w, n = 32, 48, 3
    clip = tmp_path / "clip"
    p = subprocess.run([sys.executable, "-m", "gst_plugins.cli", "simulate", "synthetic", "-o", str(clip), "--cfa",
                        "grbg", "--frames", str(n), "--width", str(w), "--height", str(h)], capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr
    prof = dc.replace(profile.load(clip / "camera.json"), white_balance=(1.2, 1.0, 0.9))
    path = tmp_path / "camera.json"
    profile.save(prof, path)
    prof = profile.load(path)
    src = batch.open_source(clip)
    raws = [batch.read_frame(src.raw, w, h, i) for i in range(n)]
    from gi.repository import Gst
    bufs = []
    for i, r in enumerate(raws):
        b = Gst.Buffer.new_wrapped(np.ascontiguousarray(r, "<u2").tobytes())
        b.pts, b.duration = i * DUR, DUR
        bufs.append(b)
    out, err = run_frames(f"nrvalidity profile={path} ! nrreconstruct method=preview ! nrtonemap ! "
                          f"video/x-raw,format=RGB", f"video/x-raw,format=GRAY16_LE,width={w},height={h},"
                          f"framerate={FPS}/1", bufs)
    assert err is None, err
    assert len(out) == n
    local = tonemap.LocalTonemap(0.1)
    for r, (_, data) in zip(raws, out):
        rgb, _ = chain.process_frame(r.copy(), prof, chain.ChainSettings(method="preview", crosstalk="off"))
        want = local.rgb(rgb, float(prof.white), white_balance=prof.white_balance)
        assert (np.ndarray((h, w, 3), np.uint8, data, 0, (w * 3, 3, 1)) == want).all()
