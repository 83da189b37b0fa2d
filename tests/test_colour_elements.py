"""The colour chain's elements in-process (docs/COLOUR.md "Caps and elements"): a colour sensor's raw frames
(GRAY16_LE with the CFA from the profile, or 8-bit video/x-bayer) through nrvalidity ! nrcrosstalk !
nrreconstruct become colour frames (layout rgb-f32-u8-planar) equal bit for bit to the core's
`demosaic.reconstruct_cfa`; frames out = frames in with their timestamps; every refusal is an element error
naming the element and what is wrong."""
from __future__ import annotations

import dataclasses
import json
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from test_camera import IP, RECIPE, fake_camera  # noqa: F401  (the Aravis fake camera fixture)

pytestmark = pytest.mark.gst

SEC = 1_000_000_000
FPS = 5
DUR = SEC // FPS
H, W = 48, 64
PIPELINES = Path(__file__).resolve().parent.parent / "pipelines"

# the contract (docs/ARCHITECTURE.md), written out here: state values and bits
VALID, REASON_MASK, RECONSTRUCTED = 0, 0x0F, 0x40


def colour_scene(h, w, shift=0):
    """Planar linear RGB (3, H, W) over ~4 decades: horizontal ramps of different slopes per channel and a
    vertical ripple in green, moved `shift` pixels."""
    yy, xx = np.mgrid[0:h, 0:w]
    x = (xx + shift) % w
    return np.stack([10.0 ** (0.5 + 4.5 * x / w), 10.0 ** (0.5 + 4.0 * x / w) * (1 + 0.3 * np.sin(yy / 5.0)),
                     10.0 ** (0.3 + 4.2 * (w - x) / w)]).astype(np.float32)


def colour_raws(prof, n=3, seed=1):
    """Raw frames of a colour sensor: sensor.capture of the CFA mosaic of the scene."""
    from nrhdr_core import cfa, sensor
    rng = np.random.default_rng(seed)
    return [sensor.capture(cfa.mosaic(colour_scene(prof.height, prof.width, i), prof.cfa), prof, rng)
            for i in range(n)]


def save_profile(tmp_path, name, h=H, w=W, **fields):
    from nrhdr_core import profile
    path = tmp_path / f"{name}.json"
    profile.save(profile.default(h, w, seed=3, **fields), path)
    return path, profile.load(path)


@pytest.fixture
def colour12(tmp_path):
    return save_profile(tmp_path, "colour12", cfa="rggb")


@pytest.fixture
def colour8(tmp_path):
    return save_profile(tmp_path, "colour8", cfa="rggb", bit_depth=8, clip_code=250, l_min=4.0)


def gray16_caps(w=W, h=H):
    return f"video/x-raw,format=GRAY16_LE,width={w},height={h},framerate={FPS}/1"


def bayer_caps(fmt, w=W, h=H):
    return f"video/x-bayer,format={fmt},width={w},height={h},framerate={FPS}/1"


def make_buffers(frames, flags=None):
    from gi.repository import Gst
    out = []
    for i, data in enumerate(frames):
        b = Gst.Buffer.new_wrapped(bytes(data))
        b.pts, b.duration = i * DUR, DUR
        if flags and i in flags:
            b.set_flags(flags[i])
        out.append(b)
    return out


def run(desc, caps, buffers, timeout=900.0):
    """appsrc (caps) ! desc ! appsink: [(caps string, pts, duration, flags, bytes)], (element, error text) or None,
    element messages. `timeout` covers a cold numba cache (nrreconstruct compiles the demosaic kernels when it
    first sees mosaic caps)."""
    from gi.repository import Gst, GstApp  # noqa: F401
    p = Gst.parse_launch(f"appsrc name=src format=time ! {desc} ! appsink name=sink sync=false")
    src, sink = p.get_by_name("src"), p.get_by_name("sink")
    src.set_property("caps", Gst.Caps.from_string(caps))
    bus = p.get_bus()
    samples, error, messages = [], None, []

    def drain():
        nonlocal error
        while (m := bus.pop()) is not None:
            if m.type == Gst.MessageType.ERROR and error is None:
                error = (m.src.get_name(), m.parse_error()[0].message)
            elif m.type == Gst.MessageType.ELEMENT:
                messages.append(m.get_structure().copy())

    try:
        p.set_state(Gst.State.PLAYING)
        for b in buffers:
            if src.push_buffer(b) != Gst.FlowReturn.OK:
                break
        src.end_of_stream()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            drain()
            if error is not None:
                break
            smp = sink.try_pull_sample(50 * Gst.MSECOND)
            if smp is not None:
                b = smp.get_buffer()
                ok, mi = b.map(Gst.MapFlags.READ)
                assert ok
                data = bytes(mi.data)
                b.unmap(mi)
                samples.append((smp.get_caps().to_string(), b.pts, b.duration, b.get_flags(), data))
            elif sink.is_eos():
                break
        drain()
    finally:
        p.set_state(Gst.State.NULL)
        drain()
    return samples, error, messages


def pull_all(desc, timeout_s=900):
    """Every sample of the appsink `sink` of pipeline `desc` until EOS: [(caps string, pts, bytes)]; an error
    on the bus fails the test."""
    from gi.repository import Gst
    pl = Gst.parse_launch(desc)
    sink = pl.get_by_name("sink")
    got = []
    try:
        pl.set_state(Gst.State.PLAYING)
        while (smp := sink.try_pull_sample(timeout_s * Gst.SECOND)) is not None:
            b = smp.get_buffer()
            ok, mi = b.map(Gst.MapFlags.READ)
            assert ok
            got.append((smp.get_caps().to_string(), b.pts, bytes(mi.data)))
            b.unmap(mi)
        m = pl.get_bus().pop_filtered(Gst.MessageType.ERROR)
        assert m is None, m.parse_error()[0].message
    finally:
        pl.set_state(Gst.State.NULL)
    return got


def colour_frame(data, h=H, w=W):
    """(rgb (3, H, W) float32, state (H, W) uint8) of a rgb-f32-u8-planar frame, read per the contract:
    float32 planes R, G, B (row-major, no padding) then the state plane, 13*W*H bytes in all."""
    n = h * w
    assert len(data) == 13 * n, f"colour frame of {len(data)} bytes, {w}x{h} needs {13 * n}"
    rgb = np.frombuffer(data, "<f4", count=3 * n).reshape(3, h, w)
    state = np.frombuffer(data, np.uint8, offset=12 * n).reshape(h, w)
    return rgb, state


def core_rgb(raw16, prof, method, preset, mode="threshold", dark_policy="weighted", fusion="auto"):
    """The core's calls, one by one, as the elements' defaults make them."""
    from nrhdr_core import crosstalk, demosaic, validity
    values, state = validity.classify(raw16, prof, mode=mode, dark_policy=dark_policy)
    v2, s2 = crosstalk.correct(values, state, prof, "kernel", lut="compact")
    state = s2.copy()
    rgb = demosaic.reconstruct_cfa(np.array(v2, np.float32), state, prof.cfa, method=method, preset=preset,
                                   use_bounds=True, noise=prof, fusion=fusion)
    return rgb, state


# ---- GRAY16_LE with the CFA from the profile --------------------------------------------------------------

@pytest.mark.parametrize("method,preset", [("preview", "balanced"), ("fse", "fast")])
def test_colour_output_equals_reconstruct_cfa_bit_for_bit(gst, colour12, method, preset):
    path, prof = colour12
    raws = colour_raws(prof)
    samples, err, _ = run(f"nrvalidity profile={path} ! nrcrosstalk ! nrreconstruct method={method} "
                          f"preset={preset}", gray16_caps(), make_buffers(r.astype("<u2").tobytes() for r in raws))
    assert err is None, err
    assert len(samples) == len(raws)
    for (caps, _pts, _dur, _flags, data), raw in zip(samples, raws):
        assert "layout=(string)rgb-f32-u8-planar" in caps and "cfa=(string)rggb" in caps
        rgb, state = colour_frame(data)
        want, want_state = core_rgb(raw, prof, method, preset)
        assert np.array_equal(rgb, want)
        assert np.array_equal(state, want_state)
        # the state is the mosaic's: RECONSTRUCTED exactly where a photosite was missing
        missing = (want_state & REASON_MASK) != VALID
        assert missing.any() and np.array_equal((state & RECONSTRUCTED) != 0, missing)
        assert np.isfinite(rgb).all()


def test_chain_process_frame_is_the_element_chain(gst, colour12):
    """nrhdr_core.chain.process_frame (batch) gives the element chain's colour frame."""
    from nrhdr_core import chain
    path, prof = colour12
    raws = colour_raws(prof, n=2)
    samples, err, _ = run(f"nrvalidity profile={path} ! nrcrosstalk ! nrreconstruct method=fse preset=fast",
                          gray16_caps(), make_buffers(r.astype("<u2").tobytes() for r in raws))
    assert err is None, err
    for (_c, _p, _d, _f, data), raw in zip(samples, raws):
        rgb, state = colour_frame(data)
        v, s = chain.process_frame(raw, prof, chain.ChainSettings(method="fse", preset="fast"))
        assert v.shape == (3, H, W)
        assert np.array_equal(rgb, v) and np.array_equal(state, s)
    with pytest.raises(ValueError, match="method 'linear'"):
        chain.process_frame(raws[0], prof, chain.ChainSettings(method="linear"))
    with pytest.raises(ValueError, match="temporal 'on'"):
        chain.process_frame(raws[0], prof, chain.ChainSettings(method="preview", temporal="on"))


def test_frames_out_equal_frames_in_with_timestamps_and_flags(gst, colour12):
    from gi.repository import Gst
    path, prof = colour12
    raws = colour_raws(prof, n=4)
    bufs = make_buffers((r.astype("<u2").tobytes() for r in raws), flags={2: Gst.BufferFlags.DELTA_UNIT})
    samples, err, _ = run(f"nrvalidity profile={path} ! nrcrosstalk ! nrreconstruct method=preview",
                          gray16_caps(), bufs)
    assert err is None, err
    assert [s[1] for s in samples] == [i * DUR for i in range(4)]
    assert [s[2] for s in samples] == [DUR] * 4
    assert [bool(s[3] & Gst.BufferFlags.DELTA_UNIT) for s in samples] == [False, False, True, False]


def test_post_stats_and_auto_on_a_colour_stream(gst, colour12):
    path, prof = colour12
    raws = colour_raws(prof, n=3)
    samples, err, msgs = run(f"nrvalidity profile={path} ! nrcrosstalk mode=off ! nrreconstruct method=auto "
                             f"post-stats=true", gray16_caps(), make_buffers(r.astype("<u2").tobytes() for r in raws))
    assert err is None, err
    stats = [m for m in msgs if m.get_name() == "nrhdr-frame-stats"]
    assert len(stats) == len(samples) == 3
    for m, (_c, _p, _d, _f, data) in zip(stats, samples):
        _rgb, state = colour_frame(data)
        share = np.count_nonzero(state & RECONSTRUCTED) / state.size
        assert m.get_double("missing")[1] == pytest.approx(share)
        assert m.get_string("method") in ("fse", "preview")


def test_monochrome_profile_stays_monochrome(gst, tmp_path):
    path, prof = save_profile(tmp_path, "mono")
    from nrhdr_core import sensor
    raw = sensor.capture(colour_scene(H, W)[1], prof, np.random.default_rng(0))
    samples, err, _ = run(f"nrvalidity profile={path} ! nrcrosstalk ! nrreconstruct method=preview",
                          gray16_caps(), make_buffers([raw.astype("<u2").tobytes()]))
    assert err is None, err
    caps, _p, _d, _f, data = samples[0]
    assert "layout=(string)f32-u8-planar" in caps and "cfa" not in caps
    assert len(data) == 5 * H * W


# ---- 8-bit Bayer caps ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("width,stride", [(64, 64), (62, 62), (62, 64)])
def test_bayer8_caps_equal_the_gray16_path(gst, tmp_path, width, stride):
    """video/x-bayer 8-bit (rows of W bytes, or of W rounded up to 4 as GStreamer's Bayer elements write)
    gives the same colour frames as the codes sent as GRAY16_LE."""
    from nrhdr_core import chain
    path, prof = save_profile(tmp_path, "c8", w=width, cfa="gbrg", bit_depth=8, clip_code=250, l_min=4.0)
    raws = colour_raws(prof, n=2)
    assert max(int(r.max()) for r in raws) <= 255
    frames = []
    for r in raws:
        rows = np.zeros((H, stride), np.uint8)
        rows[:, :width] = r
        frames.append(rows.tobytes())
    samples, err, _ = run(f"nrvalidity profile={path} ! nrcrosstalk ! nrreconstruct method=preview",
                          bayer_caps("gbrg", w=width), make_buffers(frames))
    assert err is None, err
    assert len(samples) == 2
    for (caps, _p, _d, _f, data), r in zip(samples, raws):
        assert "cfa=(string)gbrg" in caps
        rgb, state = colour_frame(data, w=width)
        v, s = chain.process_frame(r, prof, chain.ChainSettings(method="preview", preset="balanced"))
        assert np.array_equal(rgb, v) and np.array_equal(state, s)


def test_videotestsrc_bayer_runs(gst, colour8):
    from gi.repository import Gst
    path, _ = colour8
    p = Gst.parse_launch(f"videotestsrc num-buffers=3 ! video/x-bayer,width={W},height={H} ! nrvalidity "
                         f"profile={path} ! nrreconstruct method=preview ! fakesink name=sink")
    try:
        p.set_state(Gst.State.PLAYING)
        m = p.get_bus().timed_pop_filtered(900 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
        assert m is not None and m.type == Gst.MessageType.EOS, m and m.parse_error()[0].message
        caps = p.get_by_name("sink").sinkpads[0].get_current_caps().to_string()
        assert "rgb-f32-u8-planar" in caps and "cfa=(string)rggb" in caps
    finally:
        p.set_state(Gst.State.NULL)


# ---- refusals: element errors naming the element and what is wrong ---------------------------------------

def test_bayer_format_must_be_the_profiles_cfa(gst, colour8):
    path, _ = colour8
    _s, err, _ = run(f"nrvalidity profile={path}", bayer_caps("grbg"),
                     make_buffers([bytes(W * H)]))
    assert err is not None and err[0].startswith("nrvalidity")
    assert "format=grbg" in err[1] and "cfa rggb" in err[1] and "colour8.json" in err[1]


def test_bayer8_caps_need_an_8bit_profile(gst, colour12):
    path, _ = colour12
    _s, err, _ = run(f"nrvalidity profile={path}", bayer_caps("rggb"), make_buffers([bytes(W * H)]))
    assert err is not None and err[0].startswith("nrvalidity")
    assert "8-bit" in err[1] and "bit_depth 12" in err[1] and "colour12.json" in err[1]


def test_bayer_caps_need_a_colour_profile(gst, tmp_path):
    path, _ = save_profile(tmp_path, "mono8", bit_depth=8, clip_code=250, l_min=4.0)
    _s, err, _ = run(f"nrvalidity profile={path}", bayer_caps("rggb"), make_buffers([bytes(W * H)]))
    assert err is not None and err[0].startswith("nrvalidity")
    assert "monochrome" in err[1] and "cfa none" in err[1]


def test_bayer_buffer_of_the_wrong_size(gst, colour8):
    path, _ = colour8
    _s, err, _ = run(f"nrvalidity profile={path}", bayer_caps("rggb"), make_buffers([bytes(W * H - 7)]))
    assert err is not None and err[0].startswith("nrvalidity")
    assert f"{W * H - 7} bytes" in err[1] and str(W * H) in err[1] and "Bayer" in err[1]


@pytest.mark.parametrize("prop,text", [("temporal=on", "temporal=on"), ("method=linear", "method=linear"),
                                       ("method=nearest", "method=nearest")])
def test_monochrome_only_settings_refused_on_a_colour_stream(gst, colour12, prop, text):
    path, prof = colour12
    raws = colour_raws(prof, n=1)
    _s, err, _ = run(f"nrvalidity profile={path} ! nrreconstruct {prop}", gray16_caps(),
                     make_buffers([raws[0].astype("<u2").tobytes()]))
    assert err is not None and err[0].startswith("nrreconstruct")
    assert text in err[1] and "cfa=rggb" in err[1]


def test_wrong_buffer_size_for_the_colour_chain(gst):
    """A mosaic stream (cfa in the caps) whose buffer holds a colour frame's bytes: nrreconstruct names both
    sizes and the layout the bytes would fit."""
    n = W * H
    caps = f"other/x-nrhdr,layout=(string)f32-u8-planar,cfa=(string)rggb,width={W},height={H},framerate={FPS}/1"
    _s, err, _ = run("nrreconstruct method=preview", caps, make_buffers([bytes(13 * n)]))
    assert err is not None and err[0].startswith("nrreconstruct")
    assert f"{13 * n} bytes" in err[1] and f"expected {5 * n} bytes" in err[1] and "rgb-f32-u8-planar" in err[1]


def test_colour_frames_refused_where_mosaic_frames_are_needed(gst):
    n = W * H
    caps = f"other/x-nrhdr,layout=(string)rgb-f32-u8-planar,cfa=(string)rggb,width={W},height={H},framerate={FPS}/1"
    for element in ("nrcrosstalk", "nrreconstruct"):
        _s, err, _ = run(element, caps, make_buffers([bytes(13 * n)]))
        assert err is not None and err[0].startswith(element)
        assert "rgb-f32-u8-planar" in err[1] and "f32-u8-planar" in err[1]


def test_colour_layout_helpers(gst):
    """The caps and buffer helpers of the colour layout (public names of gst_plugins.elements._common)."""
    from gi.repository import Gst
    from gst_plugins.elements._common import FrameSizeError, HdrInfo, HdrPool, LAYOUTS, alloc_hdr_buffer, map_hdr
    caps = Gst.Caps.from_string(f"other/x-nrhdr,layout=(string)rgb-f32-u8-planar,cfa=(string)bggr,width=8,"
                                f"height=6,framerate={FPS}/1")
    info = HdrInfo.from_caps(caps, LAYOUTS)
    assert (info.channels, info.size, info.state_offset, info.cfa) == (3, 13 * 48, 12 * 48, "bggr")
    buf = HdrPool(info).acquire()
    assert buf.get_size() == 13 * 48
    with map_hdr(buf, info, write=True) as (values, state):
        assert values.shape == (3, 6, 8) and state.shape == (6, 8)
        values[...] = np.arange(3 * 48, dtype=np.float32).reshape(3, 6, 8)
        state[...] = 7
    ok, mi = buf.map(Gst.MapFlags.READ)
    data = bytes(mi.data)
    buf.unmap(mi)
    assert np.array_equal(np.frombuffer(data, "<f4", count=3 * 48), np.arange(3 * 48, dtype=np.float32))
    assert set(data[12 * 48:]) == {7}
    with pytest.raises(FrameSizeError, match=f"expected {13 * 48} bytes"):
        with map_hdr(alloc_hdr_buffer(8, 6), info, write=False):
            pass
    mono = HdrInfo.from_caps(Gst.Caps.from_string("other/x-nrhdr,width=8,height=6,cfa=(string)rggb"))
    assert (mono.channels, mono.size, mono.cfa) == (1, 5 * 48, "rggb")
    with pytest.raises(ValueError, match="nrx cannot take other/x-nrhdr layout rgb-f32-u8-planar"):
        HdrInfo.from_caps(caps, element="nrx")


# ---- the recipe ------------------------------------------------------------------------------------------

def write_colour_clip(d: Path, prof, raws):
    """A clip folder as `nrhdr simulate --cfa` writes it: clip.raw (GRAY16_LE mosaic), camera.json (cfa),
    clip.json."""
    from nrhdr_core import profile
    d.mkdir(parents=True, exist_ok=True)
    profile.save(prof, d / "camera.json")
    (d / "clip.raw").write_bytes(b"".join(r.astype("<u2").tobytes() for r in raws))
    (d / "clip.json").write_text(json.dumps(
        {"format": "nrhdr-clip", "version": 2, "width": W, "height": H, "fps": FPS, "frames": len(raws),
         "raw": "clip.raw", "pixel_format": "GRAY16_LE", "profile": "camera.json", "cfa": "rggb",
         "nd_layout": "independent", "sensitivity": [1, 1, 1]}))


def test_colour_recipe(gst, gst_subprocess_env, colour12, tmp_path):
    """pipelines/colour_to_exr.sh: a colour clip's frames, DRY_RUN=1 prints the pipeline, which runs up to
    the colour frames here (fakesink); the EXR files when nrexrsink takes colour frames."""
    from gi.repository import Gst
    path, prof = colour12
    raws = colour_raws(prof, n=3)
    clip = tmp_path / "clip"
    write_colour_clip(clip, prof, raws)
    env = dict(gst_subprocess_env, DRY_RUN="1")
    p = subprocess.run(["bash", str(PIPELINES / "colour_to_exr.sh"), str(clip), str(tmp_path / "exr")], env=env,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    desc = p.stdout.strip()
    assert "nrreconstruct" in desc and "layout=rgb-f32-u8-planar" in desc and "nrexrsink" in desc
    head = desc[:desc.index("! nrexrsink")]
    frames = [data for _c, _p, data in pull_all(head + " ! appsink name=sink sync=false")]
    assert len(frames) == 3
    for data, raw in zip(frames, raws):
        rgb, state = colour_frame(data)
        want, want_state = core_rgb(raw, prof, "fse", "fast")
        assert np.array_equal(rgb, want) and np.array_equal(state, want_state)
    sink_tmpl = Gst.ElementFactory.find("nrexrsink").get_static_pad_templates()[0].get_caps().to_string()
    if "rgb-f32-u8-planar" not in sink_tmpl:
        pytest.skip("nrexrsink does not take colour frames in this tree")
    p = subprocess.run(["bash", str(PIPELINES / "colour_to_exr.sh"), str(clip), str(tmp_path / "exr")],
                       env=gst_subprocess_env, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr
    from nrhdr_core import io
    files = sorted((tmp_path / "exr").glob("frame_*.exr"))
    assert len(files) == 3
    v = io.read_exr(files[0])
    v = v[0] if isinstance(v, tuple) else v
    assert np.asarray(v).shape == (3, H, W)
    assert np.array_equal(np.asarray(v), core_rgb(raws[0], prof, "fse", "fast")[0])


def test_colour_recipe_refuses_a_monochrome_clip(gst_subprocess_env, tiny_clip, tmp_path):
    d, _prof, _raws = tiny_clip
    p = subprocess.run(["bash", str(PIPELINES / "colour_to_exr.sh"), str(d), str(tmp_path / "exr")],
                       env=gst_subprocess_env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert "monochrome" in p.stderr and "raw_to_exr.sh" in p.stderr


def test_crosstalk_profile_of_another_cfa_refused(gst, colour12, tmp_path):
    path, prof = colour12
    other, _ = save_profile(tmp_path, "bggr", cfa="bggr")
    _s, err, _ = run(f"nrvalidity profile={path} ! nrcrosstalk profile={other}", gray16_caps(),
                     make_buffers([colour_raws(prof, n=1)[0].astype("<u2").tobytes()]))
    assert err is not None and err[0].startswith("nrcrosstalk")
    assert "cfa bggr" in err[1] and "cfa=rggb" in err[1]


def test_warmup_compiles_the_colour_path():
    """chain.warmup with a CFA runs demosaic.reconstruct_cfa for the colour methods (and skips the others)."""
    from nrhdr_core import chain
    sets = [chain.ChainSettings(method=m, preset="fast") for m in ("preview", "fse", "linear")]
    chain.warmup(sets, stages=("validity", "crosstalk", "reconstruction"), elements=True, cfa="rggb")
    with pytest.raises(ValueError, match="cfa"):
        chain.warmup(sets[0], cfa="rgb")


def test_warmup_covers_the_per_colour_crosstalk():
    """After chain.warmup's crosstalk stage with a CFA, correcting a colour camera's frame whose calibration has
    per-colour amplitudes (`calibration.colour_spill`) needs no kernel signature the warm-up did not make, in
    every mode and LUT form (a new one is a compilation in nrcrosstalk, mid-stream)."""
    import itertools

    from numba.core.registry import CPUDispatcher

    from nrhdr_core import chain, crosstalk, profile, sensor, validity
    sets = [chain.ChainSettings(crosstalk=m, crosstalk_lut=f)
            for m, f in itertools.product(("lut", "kernel"), chain.LUT_FORMS)]
    chain.warmup(sets, stages=("validity", "crosstalk"), elements=True, cfa="rggb")
    kernels = [f for f in vars(crosstalk).values() if isinstance(f, CPUDispatcher)]
    warm = [set(f.signatures) for f in kernels]
    prof = profile.default(24, 32, seed=2).replace(cfa="rggb")
    calib = crosstalk.identity_calibration(prof.mask, nd=prof.nd, black_level=prof.black_level,
                                           clip_code=prof.clip_code)
    amp = np.stack([np.full((24, 32), a, np.float32) for a in (1.2, 1.0, 0.8)])
    prof = prof.replace(crosstalk=dataclasses.replace(calib, colour=amp))
    flux = np.geomspace(1.0, 3e4, 24 * 32).reshape(24, 32)
    raw = sensor.capture(flux, prof, np.random.default_rng(1))
    for s in sets:
        v, st = validity.classify(raw, prof)
        crosstalk.correct(v, st, prof, s.crosstalk, lut=s.crosstalk_lut)
    assert [sorted(map(str, set(f.signatures) - w)) for f, w in zip(kernels, warm)] == [[]] * len(kernels)


# ---- a GenICam camera's 8-bit Bayer (the Aravis fake camera) ---------------------------------------------


def test_fake_camera_bayer8_becomes_colour_frames(fake_camera, gst, tmp_path):
    """aravissrc's video/x-bayer (BayerRG8 on the camera) through nrvalidity with an 8-bit rggb profile: one
    colour frame per camera frame, timestamps rising."""
    path, _ = save_profile(tmp_path, "cam8", cfa="rggb", bit_depth=8, clip_code=250, l_min=4.0)
    got = [(c, p, len(data)) for c, p, data in pull_all(
        f"aravissrc camera-name={IP} num-buffers=3 ! {bayer_caps('rggb')} ! nrvalidity profile={path} ! "
        f"nrcrosstalk ! nrreconstruct method=preview ! appsink name=sink sync=false")]
    assert len(got) == 3
    assert all("rgb-f32-u8-planar" in c and "cfa=(string)rggb" in c and n == 13 * W * H for c, _p, n in got)
    assert [p for _c, p, _n in got] == sorted(p for _c, p, _n in got)


def test_camera_recipe_bayer_needs_a_colour_profile(gst_subprocess_env, tmp_path):
    path, _ = save_profile(tmp_path, "mono8", bit_depth=8, clip_code=250, l_min=4.0)
    p = subprocess.run(["bash", str(RECIPE), "preview"], env=dict(gst_subprocess_env, PROFILE=str(path),
                                                                     FORMAT="BAYER", CAMERA=IP),
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "FORMAT=BAYER needs a colour profile" in p.stderr
