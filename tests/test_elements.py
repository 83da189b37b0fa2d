"""The nrhdr GStreamer elements in-process (appsrc ! element ! appsink): pixel values against the paper's
Eq. 3 computed here, state codes, frames in = out, timestamps, EOS, properties changed while PLAYING."""
from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import hdr_buffer, make_test_clip, raw_buffer, run_appsrc

pytestmark = pytest.mark.gst

SEC = 1_000_000_000
FPS = 5
DUR = SEC // FPS

# state codes (docs/ARCHITECTURE.md), written out here so the test checks the contract, not the module
VALID, CLIPPED, DARK, DISCARDED = 0, 1, 2, 3
RECONSTRUCTED, ATTENUATED = 0x40, 0x80


def raw_caps(w, h, fmt="GRAY16_LE"):
    return f"video/x-raw,format={fmt},width={w},height={h},framerate={FPS}/1"


def hdr_caps(w, h, white=None, profile=None):
    c = f"other/x-nrhdr,width={w},height={h},framerate={FPS}/1"
    if white is not None:
        c += f",white=(double){white}"
    if profile is not None:
        c += f",profile=(string)\"{profile}\""
    return c


def raw_buffers(raws):
    return [raw_buffer(r, pts=i * DUR, duration=DUR) for i, r in enumerate(raws)]


def expected_threshold(raw, prof, l_min=None):
    """Paper 2.3 / Eq. 3, threshold mode, computed independently of nrhdr_core.validity."""
    lm = np.float32(prof.l_min if l_min is None else l_min)
    code = raw.astype(np.float32)
    att = prof.mask
    s = np.where(att, np.float32(prof.nd), np.float32(1.0)).astype(np.float32)
    sig = code - np.float32(prof.black_level)
    clipped = raw >= prof.clip_code
    dark = att & ~clipped & (sig < lm)
    clip_val = (np.float32(prof.clip_code) - np.float32(prof.black_level)) * s
    vals = np.where(clipped, clip_val, np.where(dark, lm * s, sig * s))
    st = np.where(clipped, CLIPPED, np.where(dark, DARK, VALID)) | np.where(att, ATTENUATED, 0)
    return vals.astype(np.float32), st.astype(np.uint8)


def zero_db(prof):
    """SNR = 0 dB signal: s^2 = g s + (g sigma_r)^2 + 1/12 (shot, read, quantisation noise)."""
    g = prof.gain
    c = (g * prof.read_noise) ** 2 + 1 / 12
    return 0.5 * (g + math.sqrt(g * g + 4 * c))


# ---- registration and metadata ------------------------------------------------------------------------

def test_register_all_is_idempotent_and_documented(gst):
    import gst_plugins
    names = gst_plugins.register_all()
    assert gst_plugins.register_all() == names
    klass = {"nrvalidity": "Filter/Converter/Video", "nrcrosstalk": "Filter/Effect/Video",
             "nrreconstruct": "Filter/Effect/Video", "nrtonemap": "Filter/Converter/Video",
             "nrexrsink": "Sink/Video", "nrcamsrc": "Source/Video", "nrimagesrc": "Source/Video",
             "nrhdrenc": "Codec/Encoder/Video"}
    assert set(names) == set(klass)
    for name, k in klass.items():
        f = gst.ElementFactory.find(name)
        assert f is not None, name
        assert f.get_metadata("klass") == k
        el = f.create(None)
        assert el.get_name() == f"{name}0" or el.get_name().startswith(name)
        own = [p for p in el.list_properties() if p.owner_type == el.__gtype__]
        assert own, name
        for p in own:
            assert p.nick and p.blurb and len(p.blurb) > 15, (name, p.name)


def test_one_class_per_element(gst):
    """The loader shims import the class from gst_plugins.elements; they never define one."""
    import importlib.util
    from pathlib import Path
    import gst_plugins
    from gst_plugins.elements import ELEMENTS, element_class
    shim_dir = Path(gst_plugins.__file__).parent / "python"
    for name in ELEMENTS:
        src = (shim_dir / f"{name}.py").read_text()
        assert "class " not in src.replace("the class lives", "")
        spec = importlib.util.spec_from_file_location(f"_shim_{name}", shim_dir / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        fname, _rank, cls = mod.__gstelementfactory__
        assert fname == name and cls is element_class(name)


# ---- nrvalidity ----------------------------------------------------------------------------------------

def test_validity_threshold_matches_eq3(gst, tiny_clip):
    d, prof, raws = tiny_clip
    h, w = prof.height, prof.width
    r = run_appsrc(f"nrvalidity profile={d / 'camera.json'} dark-policy=threshold", raw_caps(w, h), raw_buffers(raws))
    assert r.error is None, r.error_text
    assert r.eos
    assert len(r.samples) == len(raws)
    for i, (caps, pts, dur, (vals, st)) in enumerate(r.samples):
        assert pts == i * DUR and dur == DUR
        ev, es = expected_threshold(raws[i], prof)
        np.testing.assert_array_equal(st, es)
        np.testing.assert_allclose(vals, ev, rtol=1e-6)
    caps = r.samples[0][0]
    assert caps.startswith("other/x-nrhdr")
    assert f"width=(int){w}" in caps and f"height=(int){h}" in caps and "framerate=(fraction)5/1" in caps
    assert "camera.json" in caps
    # the clip has every kind of pixel
    st_all = np.stack([s[3][1] for s in r.samples]) & 0x0F
    assert {VALID, CLIPPED, DARK} <= set(np.unique(st_all).tolist())


def test_validity_white_in_caps_and_black_level(gst, tmp_path):
    d, prof, raws = make_test_clip(tmp_path / "c", width=32, height=24, frames=2, black_level=64.0)
    r = run_appsrc(f"nrvalidity profile={d / 'camera.json'} l-min=300 dark-policy=threshold", raw_caps(32, 24), raw_buffers(raws))
    assert r.error is None, r.error_text
    from gi.repository import Gst
    s = Gst.Caps.from_string(r.samples[0][0]).get_structure(0)
    assert s.get_double("white")[1] == pytest.approx((4094 - 64) * 6.35)
    for i, smp in enumerate(r.samples):
        ev, es = expected_threshold(raws[i], prof, l_min=300)
        np.testing.assert_array_equal(smp[3][1], es)
        np.testing.assert_allclose(smp[3][0], ev, rtol=1e-6)


def test_validity_mode_all_uses_zero_db_limit(gst, tiny_clip):
    d, prof, raws = tiny_clip
    r = run_appsrc(f"nrvalidity profile={d / 'camera.json'} mode=all", raw_caps(prof.width, prof.height),
                   raw_buffers(raws[:2]))
    assert r.error is None, r.error_text
    s0 = zero_db(prof)
    for i, smp in enumerate(r.samples):
        vals, st = smp[3]
        raw = raws[i].astype(np.float64)
        sig = raw - prof.black_level
        clipped = raws[i] >= prof.clip_code
        dark = ~clipped & (sig < s0)
        valid = ~clipped & ~dark
        assert np.array_equal((st & 0x0F) == CLIPPED, clipped)
        assert np.array_equal((st & 0x0F) == DARK, dark)
        assert np.array_equal((st & 0x0F) == VALID, valid)
        s = np.where(prof.mask, prof.nd, 1.0)
        np.testing.assert_allclose(vals[valid], (sig * s)[valid], rtol=1e-6)


def test_validity_mode_best_discards_attenuated_next_to_valid_regular(gst, tmp_path):
    from nrhdr_core import profile
    mask = np.zeros((8, 8), bool)
    mask[2, 2] = mask[5, 5] = True
    prof = profile.make(mask)
    profile.save(prof, tmp_path / "p.json")
    raw = np.full((8, 8), 2000, np.uint16)
    raw[4:7, 4:7] = 4095          # every regular neighbour of (5, 5) is clipped
    raw[5, 5] = 1000              # attenuated, valid, no valid regular neighbour -> kept
    raw[2, 2] = 1000              # attenuated, valid regular neighbours -> discarded
    r = run_appsrc(f"nrvalidity profile={tmp_path / 'p.json'} mode=best", raw_caps(8, 8), raw_buffers([raw]))
    assert r.error is None, r.error_text
    vals, st = r.samples[0][3]
    assert st[2, 2] == DISCARDED | ATTENUATED
    assert st[5, 5] == VALID | ATTENUATED
    assert vals[5, 5] == pytest.approx(1000 * 6.35)
    assert vals[2, 2] == pytest.approx(1000 * 6.35)   # a discarded pixel keeps its measurement
    assert st[4, 4] == CLIPPED and st[0, 0] == VALID


def test_validity_mode_change_while_playing(gst, tiny_clip):
    d, prof, raws = tiny_clip

    def before(i, pipeline):
        el = pipeline.get_by_name("v")
        if i == 2:
            el.set_property("mode", "all")
        if i == 3:
            el.set_property("l-min", 1000.0)
            el.set_property("mode", "threshold")

    r = run_appsrc(f"nrvalidity name=v profile={d / 'camera.json'} dark-policy=threshold", raw_caps(prof.width, prof.height),
                   raw_buffers(raws[:4]), before_push=before, lockstep=True)
    assert r.error is None, r.error_text
    assert len(r.samples) == 4
    np.testing.assert_array_equal(r.samples[1][3][1], expected_threshold(raws[1], prof)[1])
    assert not np.array_equal(r.samples[2][3][1], expected_threshold(raws[2], prof)[1])
    np.testing.assert_array_equal(r.samples[3][3][1], expected_threshold(raws[3], prof, l_min=1000)[1])


def test_validity_odd_width_with_plane_strides(gst, tmp_path):
    """Raw files have unpadded rows; rawvideoparse plane-strides=<2W> delivers them for odd widths."""
    d, prof, raws = make_test_clip(tmp_path / "odd", width=63, height=17, frames=2)
    import gst_plugins
    from gi.repository import Gst
    desc = (f"filesrc location={d / 'clip.raw'} ! rawvideoparse format=gray16-le width=63 height=17 "
            f"framerate=5/1 plane-strides=<126> ! nrvalidity profile={d / 'camera.json'} dark-policy=threshold ! "
            f"appsink name=sink sync=false")
    gst_plugins.register_all()
    p = Gst.parse_launch(desc)
    sink = p.get_by_name("sink")
    p.set_state(Gst.State.PLAYING)
    from conftest import sample_payload
    got = []
    for _ in range(2):
        smp = sink.try_pull_sample(10 * Gst.SECOND)
        assert smp is not None
        got.append(sample_payload(smp))
    p.set_state(Gst.State.NULL)
    for i, (vals, st) in enumerate(got):
        ev, es = expected_threshold(raws[i], prof)
        np.testing.assert_array_equal(st, es)
        np.testing.assert_allclose(vals, ev, rtol=1e-6)


# ---- nrcrosstalk ---------------------------------------------------------------------------------------

def test_crosstalk_without_calibration_is_identity(gst, tiny_clip):
    d, prof, raws = tiny_clip
    r = run_appsrc(f"nrvalidity profile={d / 'camera.json'} dark-policy=threshold ! nrcrosstalk",
                   raw_caps(prof.width, prof.height), raw_buffers(raws))
    assert r.error is None, r.error_text
    assert len(r.samples) == len(raws)
    for i, smp in enumerate(r.samples):
        ev, es = expected_threshold(raws[i], prof)
        np.testing.assert_array_equal(smp[3][1], es)
        np.testing.assert_allclose(smp[3][0], ev, rtol=1e-6)
        assert smp[1] == i * DUR and smp[2] == DUR


def test_crosstalk_data_path_calls_core_in_place(gst, tiny_clip, monkeypatch):
    """The element maps the frame writable and hands the core the arrays (here a stand-in correction)."""
    from nrhdr_core import crosstalk
    d, prof, raws = tiny_clip
    seen = []

    def fake_correct(values, state, profile, mode="lut", **kw):
        seen.append((mode, values.shape, profile.width))
        values += 1.0
        state |= 0x04
        return values, state

    monkeypatch.setattr(crosstalk, "correct", fake_correct)
    v = np.arange(prof.width * prof.height, dtype=np.float32).reshape(prof.height, prof.width)
    s = np.zeros_like(v, dtype=np.uint8)
    r = run_appsrc("nrcrosstalk mode=kernel", hdr_caps(prof.width, prof.height, 26000.0, d / "camera.json"),
                   [hdr_buffer(v, s, pts=0, duration=DUR), hdr_buffer(v, s, pts=DUR, duration=DUR)])
    assert r.error is None, r.error_text
    seen = [x for x in seen if x[1] == v.shape]          # (the core's warm-up may call it on a tiny frame)
    assert len(r.samples) == 2 and len(seen) == 2
    assert seen[0] == ("kernel", v.shape, prof.width)
    np.testing.assert_array_equal(r.samples[0][3][0], v + 1)
    np.testing.assert_array_equal(r.samples[0][3][1], s | 4)


# ---- nrreconstruct -------------------------------------------------------------------------------------

@pytest.mark.parametrize("method", ["preview", "nearest", "linear"])
def test_reconstruct_fills_missing_keeps_known(gst, tiny_clip, method):
    d, prof, raws = tiny_clip
    r = run_appsrc(f"nrvalidity profile={d / 'camera.json'} dark-policy=threshold ! nrreconstruct method={method} post-stats=true",
                   raw_caps(prof.width, prof.height), raw_buffers(raws))
    assert r.error is None, r.error_text
    assert len(r.samples) == len(raws) and r.eos
    stats = r.element_messages("nrhdr-frame-stats")
    assert len(stats) == len(raws)
    for i, smp in enumerate(r.samples):
        assert smp[1] == i * DUR and smp[2] == DUR
        vals, st = smp[3]
        ev, es = expected_threshold(raws[i], prof)
        known = (es & 0x0F) == VALID
        np.testing.assert_array_equal(vals[known], ev[known])          # measured pixels bit-exact
        np.testing.assert_array_equal(st[known], es[known])
        np.testing.assert_array_equal(st[~known], es[~known] | RECONSTRUCTED)
        assert np.isfinite(vals).all()
        # bounds: clipped pixels at least their clip level, too-dark ones at most l_min * ND
        clipped = (es & 0x0F) == CLIPPED
        dark = (es & 0x0F) == DARK
        assert (vals[clipped] >= ev[clipped] * (1 - 1e-6)).all()
        assert (vals[dark] <= ev[dark] * (1 + 1e-6)).all()
        s = stats[i]
        assert s.get_value("frame") == i
        assert s.get_value("method") == method
        assert s.get_value("missing") == pytest.approx(float(np.mean(~known)))
        assert s.get_value("seconds") >= 0
    from gi.repository import GObject
    assert stats[0].get_field_type("frame") == GObject.TYPE_UINT64
    assert stats[0].get_field_type("missing") == GObject.TYPE_DOUBLE


def test_reconstruct_method_and_preset_change_while_playing(gst, tiny_clip):
    d, prof, raws = tiny_clip
    from gi.repository import Gst
    el = Gst.ElementFactory.make("nrreconstruct", None)
    for pname in ("method", "preset", "use-bounds", "noise-fusion"):
        assert el.find_property(pname).flags & Gst.PARAM_MUTABLE_PLAYING, pname

    def before(i, pipeline):
        el = pipeline.get_by_name("r")
        if i == 1:
            el.set_property("method", "nearest")
        if i == 2:
            el.set_property("method", "linear")
            el.set_property("preset", "best")
        if i == 3:
            with pytest.raises(TypeError, match="no-such-method"):   # an enum: refused, value kept
                el.set_property("method", "no-such-method")
            el.set_property("use-bounds", False)
            assert el.get_property("method").value_nick == "linear"
            el.set_property("method", 99)                           # out of the enum: a WARNING

    r = run_appsrc(f"nrvalidity profile={d / 'camera.json'} ! nrreconstruct name=r method=preview "
                   f"post-stats=true",
                   raw_caps(prof.width, prof.height), raw_buffers(raws[:4]), before_push=before,
                   lockstep=True)
    assert r.error is None, r.error_text
    methods = [s.get_value("method") for s in r.element_messages("nrhdr-frame-stats")]
    assert methods == ["preview", "nearest", "linear", "linear"]
    warnings = [m for m in r.messages if m.type == Gst.MessageType.WARNING]
    assert any("property 'method'" in m.parse_warning()[0].message and "fse, linear" in
               m.parse_warning()[0].message for m in warnings)


@pytest.mark.parametrize("method", ["preview", "fse"])
def test_reconstruct_noise_fusion_setting_reaches_the_core(gst, tiny_clip, method):
    """noise-fusion=fast|accurate: each frame equals the core's per-frame path with that fusion setting
    (nrvalidity's default dark-policy=weighted makes NOISY pixels), and the two settings differ there."""
    from nrhdr_core import chain, reconstruction
    import gst_plugins.elements.nrreconstruct as nrrec
    assert nrrec.PROPERTIES["noise-fusion"].choices == reconstruction.FUSIONS
    d, prof, raws = tiny_clip
    out = {}
    for setting in reconstruction.FUSIONS:
        r = run_appsrc(f"nrvalidity profile={d / 'camera.json'} ! nrreconstruct method={method} preset=fast "
                       f"noise-fusion={setting}", raw_caps(prof.width, prof.height), raw_buffers(raws[:2]))
        assert r.error is None, r.error_text
        assert len(r.samples) == 2
        out[setting] = [smp[3][0] for smp in r.samples]
        for i, vals in enumerate(out[setting]):
            ev, es = chain.process_frame(raws[i], prof, chain.ChainSettings(
                crosstalk="off", method=method, preset="fast", noise_fusion=setting))
            np.testing.assert_array_equal(vals, ev)
    _, es = chain.process_frame(raws[0], prof, chain.ChainSettings(crosstalk="off", method=method))
    assert ((es & 0x0F) == 5).any()                              # there are NOISY pixels to fuse
    assert not np.array_equal(out["fast"][0], out["accurate"][0])
    # auto (the default): the fast fusion for the live preview, the accurate one for the other methods
    np.testing.assert_array_equal(out["auto"][0], out["fast" if method == "preview" else "accurate"][0])


def test_reconstruct_error_is_posted_not_swallowed(gst, tiny_clip, monkeypatch):
    from nrhdr_core import reconstruction
    d, prof, raws = tiny_clip

    def boom(*a, **k):
        raise RuntimeError("synthetic failure")

    def before(i, pipeline):
        if i == 0:  # after start (whose warm-up calls the real function); the element's frame path
            monkeypatch.setattr(reconstruction, "reconstruct_frame", boom)

    r = run_appsrc(f"nrvalidity profile={d / 'camera.json'} ! nrreconstruct method=preview",
                   raw_caps(prof.width, prof.height), raw_buffers(raws), before_push=before)
    assert r.error is not None
    assert r.error[0] == "nrreconstruct0" or r.error[0].startswith("nrreconstruct")
    assert "synthetic failure" in r.error[1] and "method=preview" in r.error[1]
    assert len(r.samples) == 0


# ---- nrtonemap -----------------------------------------------------------------------------------------

def expected_log(values, white, exposure=0.0, q=1000.0, maxcode=255):
    x = np.clip(values.astype(np.float64) * 2.0 ** exposure / white, 0, 1)
    return np.floor(np.log1p(q * x) / np.log1p(q) * maxcode + 0.5)


@pytest.mark.parametrize("fmt,maxcode", [("GRAY8", 255), ("GRAY16_LE", 65535)])
def test_tonemap_log_curve_and_formats(gst, fmt, maxcode):
    h, w = 6, 62                      # GRAY8 rows are padded to 64 bytes: strided output
    white = 4094 * 6.35
    v = np.geomspace(1.0, white * 2, h * w).astype(np.float32).reshape(h, w)
    v[0, 0] = -5.0
    s = np.zeros((h, w), np.uint8)
    bufs = [hdr_buffer(v, s, pts=i * DUR, duration=DUR) for i in range(3)]
    r = run_appsrc(f"nrtonemap operator=log ! video/x-raw,format={fmt}", hdr_caps(w, h, white), bufs)
    assert r.error is None, r.error_text
    assert len(r.samples) == 3
    exp = expected_log(v, white, maxcode=maxcode)
    for i, (caps, pts, dur, img) in enumerate(r.samples):
        assert f"format=(string){fmt}" in caps
        assert pts == i * DUR and dur == DUR
        assert img.shape == (h, w)
        assert np.abs(img.astype(np.int64) - exp).max() <= 1
        assert img[0, 0] == 0 and img[-1, -1] == maxcode


def test_tonemap_fixed_white_exposure_contrast_while_playing(gst):
    h, w = 4, 16
    v = np.geomspace(10.0, 20000.0, h * w).astype(np.float32).reshape(h, w)
    s = np.zeros((h, w), np.uint8)
    bufs = [hdr_buffer(v, s, pts=i * DUR, duration=DUR) for i in range(3)]

    def before(i, pipeline):
        el = pipeline.get_by_name("t")
        if i == 1:
            el.set_property("exposure", 1.0)
        if i == 2:
            el.set_property("normalise", "fixed")
            el.set_property("white", 5000.0)
            el.set_property("contrast", 10.0)

    r = run_appsrc("nrtonemap name=t operator=log", hdr_caps(w, h, 26000.0), bufs, before_push=before,
                   lockstep=True)
    assert r.error is None, r.error_text
    imgs = [smp[3].astype(np.int64) for smp in r.samples]
    assert np.abs(imgs[0] - expected_log(v, 26000.0)).max() <= 1
    assert np.abs(imgs[1] - expected_log(v, 26000.0, exposure=1.0)).max() <= 1
    assert np.abs(imgs[2] - expected_log(v, 5000.0, exposure=1.0, q=10.0)).max() <= 1


def test_tonemap_exposure_follows_a_controller_curve(gst):
    """exposure is GST_PARAM_CONTROLLABLE: a GstController curve sets it per frame (by stream time)."""
    import gi
    try:
        gi.require_version("GstController", "1.0")
        from gi.repository import GstController
    except (ValueError, ImportError):
        pytest.skip("GstController introspection data missing")
    h, w = 4, 16
    v = np.geomspace(10.0, 20000.0, h * w).astype(np.float32).reshape(h, w)
    s = np.zeros((h, w), np.uint8)
    bufs = [hdr_buffer(v, s, pts=i * DUR, duration=DUR) for i in range(3)]
    cs = GstController.InterpolationControlSource()
    cs.set_property("mode", GstController.InterpolationMode.NONE)   # steps
    cs.set(0, 0.0)
    cs.set(DUR, 2.0)
    cs.set(2 * DUR, -1.0)

    def before(i, pipeline):
        if i == 0:
            el = pipeline.get_by_name("t")
            el.add_control_binding(GstController.DirectControlBinding.new_absolute(el, "exposure", cs))

    r = run_appsrc("nrtonemap name=t operator=log", hdr_caps(w, h, 26000.0), bufs, before_push=before,
                   lockstep=True)
    assert r.error is None, r.error_text
    for img, ev in zip([smp[3].astype(np.int64) for smp in r.samples], (0.0, 2.0, -1.0)):
        assert np.abs(img - expected_log(v, 26000.0, exposure=ev)).max() <= 1, ev


def test_tonemap_smoothed_white_does_not_flicker(gst):
    h, w = 8, 8
    s = np.zeros((h, w), np.uint8)
    base = np.linspace(100, 1000, h * w, dtype=np.float32).reshape(h, w)
    frames = [base] * 3 + [base * 4] * 3          # a sudden 2-stop brightening
    bufs = [hdr_buffer(f, s, pts=i * DUR, duration=DUR) for i, f in enumerate(frames)]
    r = run_appsrc("nrtonemap operator=log normalise=smoothed smoothing=0.3", hdr_caps(w, h), bufs)
    assert r.error is None, r.error_text
    means = [float(smp[3].mean()) for smp in r.samples]
    assert means[0] == means[1] == means[2]                 # steady scene, steady picture
    assert means[3] > means[4] > means[5] > means[2]        # adapts gradually, no jump back
    # a per-frame min/max normaliser would show frame 3 exactly like frame 0
    assert means[3] != pytest.approx(means[0], abs=0.5)


def test_tonemap_without_white_in_caps_uses_the_automatic_white(gst):
    from nrhdr_core import tonemap
    h, w = 8, 16
    v = np.geomspace(1.0, 5000.0, h * w).astype(np.float32).reshape(h, w)
    s = np.zeros((h, w), np.uint8)
    r = run_appsrc("nrtonemap operator=log", hdr_caps(w, h), [hdr_buffer(v, s, pts=0, duration=DUR)])
    assert r.error is None, r.error_text
    assert np.abs(r.samples[0][3].astype(np.int64) - expected_log(v, tonemap.auto_white(v))).max() <= 1


def test_tonemap_fixed_without_white_fails_clearly(gst):
    v = np.ones((4, 4), np.float32)
    s = np.zeros((4, 4), np.uint8)
    r = run_appsrc("nrtonemap normalise=fixed", hdr_caps(4, 4), [hdr_buffer(v, s, pts=0, duration=DUR)])
    assert r.error is not None and r.error[0].startswith("nrtonemap")
    assert "white" in r.error[1]


@pytest.mark.parametrize("fmt,dtype", [("GRAY8", np.uint8), ("GRAY16_LE", np.uint16)])
def test_tonemap_local_operator_is_the_core_operator_over_frames(gst, fmt, dtype):
    """operator=local (the default) in a pipeline: frame for frame the core `LocalTonemap` with the
    element's smoothing, normalised by the caps' white; strided GRAY8 rows."""
    from nrhdr_core import tonemap
    h, w = 30, 62
    yy, xx = np.mgrid[0:h, 0:w]
    base = (np.geomspace(5.0, 40000.0, h * w).reshape(h, w) * 2.0 ** (0.4 * np.sin(xx / 2.0))).astype(np.float32)
    frames = [base, base * 2, base * 2]
    s = np.zeros((h, w), np.uint8)
    bufs = [hdr_buffer(f, s, pts=i * DUR, duration=DUR) for i, f in enumerate(frames)]
    r = run_appsrc(f"nrtonemap smoothing=0.5 ! video/x-raw,format={fmt}", hdr_caps(w, h, 26000.0), bufs)
    assert r.error is None, r.error_text
    op = tonemap.LocalTonemap(speed=0.5)
    for (_caps, _pts, _dur, img), f in zip(r.samples, frames):
        assert np.array_equal(img, op(f, 26000.0, dtype=dtype))
    assert r.samples[1][3].mean() != r.samples[2][3].mean()       # still adapting: smoothed, not per frame


def test_tonemap_operator_is_an_enum(gst):
    from gst_plugins.elements.nrtonemap import PROPERTIES
    assert PROPERTIES["operator"].choices == ("log", "local")
    assert PROPERTIES.check("operator", "fancy")[1] == "invalid value 'fancy' for property 'operator' (one of log, local)"
    el = gst.ElementFactory.make("nrtonemap", None)
    assert el.get_property("operator").value_nick == "local"
    el.set_property("operator", "log")
    assert el.get_property("operator").value_nick == "log"


# ---- nrexrsink -----------------------------------------------------------------------------------------

def _run_to_exr(gst, desc, caps, bufs):
    from gi.repository import Gst
    p = Gst.parse_launch(f"appsrc name=src format=time ! {desc}")
    src = p.get_by_name("src")
    src.set_property("caps", Gst.Caps.from_string(caps))
    p.set_state(Gst.State.PLAYING)
    for b in bufs:
        src.push_buffer(b)
    src.end_of_stream()
    msg = p.get_bus().timed_pop_filtered(30 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    p.set_state(Gst.State.NULL)
    assert msg is not None
    return msg


@pytest.mark.parametrize("write_state", [True, False])
def test_exrsink_writes_sequence(gst, tmp_path, write_state):
    from nrhdr_core import io
    h, w = 6, 10
    rng = np.random.default_rng(1)
    frames = [(rng.uniform(0, 30000, (h, w)).astype(np.float32),
               rng.choice(np.array([0, 1, 2, 0x80, 0x41, 0xC2], np.uint8), (h, w))) for _ in range(3)]
    bufs = [hdr_buffer(v, s, pts=i * DUR, duration=DUR) for i, (v, s) in enumerate(frames)]
    loc = tmp_path / "rec" / "frame_%05d.exr"
    msg = _run_to_exr(gst, f"nrexrsink location={loc} write-state={str(write_state).lower()}",
                      hdr_caps(w, h, 26000.0), bufs)
    from gi.repository import Gst
    assert msg.type == Gst.MessageType.EOS, msg.parse_error() if msg.type == Gst.MessageType.ERROR else msg
    files = sorted((tmp_path / "rec").glob("*.exr"))
    assert [f.name for f in files] == [f"frame_{i:05d}.exr" for i in range(3)]
    assert not list((tmp_path / "rec").glob(".*"))          # no temporary files left
    for f, (v, s) in zip(files, frames):
        got_v, got_s = io.read_exr(f)
        np.testing.assert_array_equal(got_v, v)
        if write_state:
            np.testing.assert_array_equal(got_s, s)
        else:
            assert got_s is None


def test_exrsink_write_error_names_file(gst, tmp_path):
    blocker = tmp_path / "blocker"
    blocker.write_text("a file where a folder should be")
    v = np.ones((4, 4), np.float32)
    s = np.zeros((4, 4), np.uint8)
    msg = _run_to_exr(gst, f"nrexrsink location={blocker}/frame_%05d.exr", hdr_caps(4, 4),
                      [hdr_buffer(v, s, pts=0, duration=DUR)])
    from gi.repository import Gst
    assert msg.type == Gst.MessageType.ERROR
    err, _ = msg.parse_error()
    assert msg.src.get_name().startswith("nrexrsink")
    assert f"{blocker}/frame_00000.exr" in err.message


# ---- the whole chain -----------------------------------------------------------------------------------

def test_full_chain_frames_timestamps_eos(gst, tiny_clip):
    d, prof, raws = tiny_clip
    r = run_appsrc(f"nrvalidity profile={d / 'camera.json'} ! nrcrosstalk ! nrreconstruct method=preview "
                   f"! nrtonemap ! video/x-raw,format=GRAY8", raw_caps(prof.width, prof.height),
                   raw_buffers(raws))
    assert r.error is None, r.error_text
    assert r.eos and len(r.samples) == len(raws)
    assert [(s[1], s[2]) for s in r.samples] == [(i * DUR, DUR) for i in range(len(raws))]
    for s in r.samples:
        assert s[3].shape == (prof.height, prof.width) and s[3].dtype == np.uint8
        assert s[3].max() > s[3].min()


def test_run_pipeline_in_process(gst, tiny_clip, tmp_path, capsys):
    from gst_plugins import runtime
    d, prof, raws = tiny_clip
    stats = []

    def on_message(msg):
        s = msg.get_structure()
        if s is not None and s.get_name() == "nrhdr-frame-stats":
            stats.append(s.get_value("missing"))

    desc = (f"filesrc location={d / 'clip.raw'} ! rawvideoparse format=gray16-le width={prof.width} "
            f"height={prof.height} framerate=5/1 ! nrvalidity profile={d / 'camera.json'} ! "
            f"nrreconstruct method=nearest post-stats=true ! nrexrsink location={tmp_path}/f_%03d.exr")
    assert runtime.run_pipeline(desc, on_message=on_message) == 0
    assert len(stats) == len(raws) and all(0 < m < 1 for m in stats)
    assert len(list(tmp_path.glob("f_*.exr"))) == len(raws)
    bad = desc.replace(f"width={prof.width}", "width=32").replace("/f_%03d", "/bad_%03d")  # new sequence
    assert runtime.run_pipeline(bad) == 1
    err = capsys.readouterr().err
    assert "nrvalidity" in err and "64x48 mask but the stream is 32x48" in err
