"""GStreamer citizenship: the one-block HDR frame through stock elements (identity dump=true,
rtpgstpay ! rtpgstdepay, filesink then filesrc ! capsfilter), caps that follow the profile (videotestsrc,
videoscale), pixel-aspect-ratio / interlace-mode pass-through, debug categories, Python warnings on the bus,
zero-copy mapping and the buffer pool."""
from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest

from conftest import hdr_buffer, hdr_bytes, run_appsrc, sample_payload

pytestmark = pytest.mark.gst

SEC = 1_000_000_000


def run_desc(gst, desc, timeout=60.0):
    """Run `<desc> ! appsink name=sink` in-process; return (samples [(caps, pts, payload)], messages)."""
    pipeline = gst.parse_launch(f"{desc} ! appsink name=sink sync=false")
    sink = pipeline.get_by_name("sink")
    bus = pipeline.get_bus()
    samples, messages = [], []

    def drain():
        while (m := bus.pop()) is not None:
            messages.append(m)
            if m.type == gst.MessageType.ERROR:
                err, dbg = m.parse_error()
                raise AssertionError(f"{m.src.get_name()}: {err.message}\n{dbg}")

    try:
        assert pipeline.set_state(gst.State.PLAYING) != gst.StateChangeReturn.FAILURE
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            drain()
            smp = sink.try_pull_sample(50 * gst.MSECOND)
            if smp is not None:
                samples.append((smp.get_caps().to_string(), smp.get_buffer().pts, sample_payload(smp)))
            elif sink.is_eos():
                break
        time.sleep(0.05)
        drain()
        assert sink.is_eos(), "no EOS"
    finally:
        pipeline.set_state(gst.State.NULL)
    drain()
    return samples, messages


def chain(d, prof, tail=""):
    return (f"filesrc location={d / 'clip.raw'} ! rawvideoparse format=gray16-le width={prof.width} "
            f"height={prof.height} framerate=5/1 plane-strides=<{2 * prof.width}> ! "
            f"nrvalidity profile={d / 'camera.json'} ! nrreconstruct method=nearest{tail}")


@pytest.fixture(scope="module")
def reference(gst, tiny_clip):
    """HDR frames and tone-mapped frames of the plain chain (no stock element in between)."""
    d, prof, raws = tiny_clip
    hdr, _ = run_desc(gst, chain(d, prof))
    mapped, _ = run_desc(gst, chain(d, prof, " ! nrtonemap ! video/x-raw,format=GRAY16_LE"))
    assert len(hdr) == len(mapped) == len(raws)
    return hdr, mapped


def test_hdr_caps_carry_the_layout(reference):
    hdr, _ = reference
    caps = hdr[0][0]
    assert caps.startswith("other/x-nrhdr") and "layout=(string)f32-u8-planar" in caps
    assert "diffuse-white=(double)" in caps and "white=(double)" in caps


@pytest.mark.parametrize("middle", ["identity dump=true", "rtpgstpay ! rtpgstdepay"])
def test_stock_elements_between_nrhdr_elements(gst, tiny_clip, reference, middle, capfd):
    """identity dump=true maps (and prints) each frame; rtpgstpay/depay serialise caps and buffers into
    RTP packets and rebuild them: the frames and their tone mapping come out bit-identical."""
    d, prof, raws = tiny_clip
    hdr_ref, mapped_ref = reference
    hdr, _ = run_desc(gst, chain(d, prof, f" ! {middle}"))
    mapped, _ = run_desc(gst, chain(d, prof, f" ! {middle} ! nrtonemap ! video/x-raw,format=GRAY16_LE"))
    assert len(hdr) == len(mapped) == len(raws)
    for (c, _, (v, s)), (c0, _, (v0, s0)) in zip(hdr, hdr_ref):
        assert "layout=(string)f32-u8-planar" in c
        assert np.array_equal(v, v0) and np.array_equal(s, s0)
    for (_, _, a), (_, _, b) in zip(mapped, mapped_ref):
        assert np.array_equal(a, b)


def test_raw_hdr_recording_plays_back(gst, tiny_clip, reference, tmp_path):
    """filesink writes the frames back to back (5*W*H bytes each); filesrc blocksize=5*W*H ! capsfilter
    reads them again: same values, same tone mapping."""
    d, prof, raws = tiny_clip
    hdr_ref, mapped_ref = reference
    rec = tmp_path / "rec.nrhdr"
    run_desc(gst, chain(d, prof, f" ! tee name=t t. ! queue ! filesink location={rec} t. ! queue"))
    frame = 5 * prof.width * prof.height
    assert rec.stat().st_size == len(raws) * frame
    data = rec.read_bytes()
    for i, (_, _, (v0, s0)) in enumerate(hdr_ref):   # the file is the documented layout, nothing else
        assert data[i * frame:(i + 1) * frame] == hdr_bytes(v0, s0)
    caps = (f"other/x-nrhdr,layout=f32-u8-planar,width={prof.width},height={prof.height},framerate=5/1,"
            f"white={prof.white}")
    mapped, _ = run_desc(gst, f"filesrc location={rec} blocksize={frame} ! capsfilter caps=\"{caps}\" ! "
                              f"nrtonemap ! video/x-raw,format=GRAY16_LE")
    assert len(mapped) == len(raws)
    for (_, _, a), (_, _, b) in zip(mapped, mapped_ref):
        assert np.array_equal(a, b)


def test_wrong_blocksize_is_a_clear_error(gst, tiny_clip, tmp_path):
    d, prof, raws = tiny_clip
    rec = tmp_path / "rec.nrhdr"
    rec.write_bytes(bytes(5 * prof.width * prof.height))
    caps = f"other/x-nrhdr,width={prof.width},height={prof.height},framerate=5/1,white=100.0"
    with pytest.raises(AssertionError) as e:
        run_desc(gst, f"filesrc location={rec} ! capsfilter caps=\"{caps}\" ! nrtonemap")
    assert "nrtonemap" in str(e.value) and f"filesrc blocksize={5 * prof.width * prof.height}" in str(e.value)


def test_old_two_block_frames_are_still_read(gst):
    v = np.geomspace(1, 1e4, 48).astype(np.float32).reshape(6, 8)
    s = np.zeros((6, 8), np.uint8)
    caps = "other/x-nrhdr,width=8,height=6,framerate=5/1,white=(double)10000"
    one = run_appsrc("nrtonemap ! video/x-raw,format=GRAY16_LE", caps, [hdr_buffer(v, s, pts=0, duration=1)])
    two = run_appsrc("nrtonemap ! video/x-raw,format=GRAY16_LE", caps,
                     [hdr_buffer(v, s, pts=0, duration=1, two_blocks=True)])
    assert one.error is None and two.error is None, (one.error_text, two.error_text)
    assert np.array_equal(one.samples[0][3], two.samples[0][3])


def test_mapping_is_zero_copy(gst):
    from gst_plugins.elements._common import HdrInfo, map_hdr
    info = HdrInfo(8, 6, 5, 1, None, None)
    v = np.arange(48, dtype=np.float32).reshape(6, 8)
    s = np.full((6, 8), 3, np.uint8)
    buf = hdr_buffer(v, s)
    with map_hdr(buf, info, write=False) as (values, state):
        assert not values.flags.writeable and not state.flags.writeable
        assert np.array_equal(values, v) and np.array_equal(state, s)
        # both planes are views into one block: the state plane starts 4*W*H bytes after the values
        assert state.ctypes.data - values.ctypes.data == 4 * 48
    with map_hdr(buf, info, write=True) as (values, state):
        values[0, 0] = -7.5
        state[5, 7] = 0x41
    ok, mi = buf.map(gst.MapFlags.READ)
    raw = bytes(mi.data)
    buf.unmap(mi)
    assert np.frombuffer(raw[:4], "<f4")[0] == -7.5 and raw[-1] == 0x41


def test_pool_recycles_frames(gst):
    from gst_plugins.elements._common import HdrInfo, HdrPool
    pool = HdrPool(HdrInfo(64, 48, 5, 1, None, None))
    seen = set()
    try:
        for _ in range(8):
            b = pool.acquire()
            assert b.n_memory() == 1 and b.get_size() == 5 * 64 * 48
            ok, mi = b.map(gst.MapFlags.READ)
            seen.add(np.frombuffer(mi.data, np.uint8).ctypes.data)
            b.unmap(mi)
            del b, mi
    finally:
        pool.close()
    assert len(seen) <= 2            # released frames come back: no allocation per frame


# ---- caps follow the profile -----------------------------------------------------------------------------

def test_videotestsrc_negotiates_the_profile_size(gst, tiny_clip):
    d, prof, _ = tiny_clip
    samples, _ = run_desc(gst, f"videotestsrc num-buffers=2 ! video/x-raw,format=GRAY16_LE ! "
                               f"nrvalidity profile={d / 'camera.json'}")
    assert len(samples) == 2
    assert f"width=(int){prof.width}" in samples[0][0] and f"height=(int){prof.height}" in samples[0][0]


def test_videoscale_scales_to_the_profile_size(gst, tiny_clip):
    d, prof, _ = tiny_clip
    samples, _ = run_desc(gst, f"videotestsrc num-buffers=2 ! video/x-raw,format=GRAY16_LE,width=320,"
                               f"height=240 ! videoscale ! nrvalidity profile={d / 'camera.json'}")
    assert len(samples) == 2
    v, s = samples[0][2]
    assert v.shape == (prof.height, prof.width)


def test_pixel_aspect_ratio_and_interlace_mode_pass_through(gst, tiny_clip):
    d, prof, _ = tiny_clip
    samples, _ = run_desc(gst, f"videotestsrc num-buffers=1 ! video/x-raw,format=GRAY16_LE,"
                               f"pixel-aspect-ratio=4/3,interlace-mode=progressive ! nrvalidity "
                               f"profile={d / 'camera.json'} ! nrreconstruct method=preview ! nrtonemap")
    caps = samples[0][0]
    assert caps.startswith("video/x-raw") and "pixel-aspect-ratio=(fraction)4/3" in caps
    assert "interlace-mode=(string)progressive" in caps


# ---- debugging -------------------------------------------------------------------------------------------

def test_debug_categories_exist(gst):
    names = {c.get_name() for c in gst.debug_get_all_categories()}
    assert {"nrvalidity", "nrcrosstalk", "nrreconstruct", "nrtonemap", "nrexrsink"} <= names


def test_gst_debug_shows_per_frame_lines(gst_subprocess_env, tiny_clip):
    d, prof, raws = tiny_clip
    env = dict(gst_subprocess_env, GST_DEBUG="nrreconstruct:6,nrvalidity:6", GST_DEBUG_NO_COLOR="1")
    p = subprocess.run(["gst-launch-1.0", *chain(d, prof).split(), "!", "fakesink"], env=env,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    lines = p.stderr.splitlines()
    for i in range(len(raws)):
        assert any(" nrreconstruct " in ln and "<nrreconstruct0>" in ln and f"frame {i} pts" in ln
                   and "filled by method=nearest" in ln for ln in lines), i
        assert any(" nrvalidity " in ln and f"frame {i} pts" in ln and "classified" in ln for ln in lines), i


def test_python_warning_becomes_a_bus_warning(gst):
    """No pixel known: reconstruction warns; the warning reaches the bus as a WARNING message from the
    element (once per run, again in the next run), the frames still come out, and warnings outside
    elements are displayed as usual (pytest.warns still sees them)."""
    from nrhdr_core import reconstruction
    v = np.zeros((4, 4), np.float32)
    s = np.full((4, 4), 1, np.uint8)        # every pixel clipped: nothing known
    for run in range(2):
        bufs = [hdr_buffer(v, s, pts=i, duration=1) for i in range(3)]
        r = run_appsrc("nrreconstruct method=nearest use-bounds=false",
                       "other/x-nrhdr,width=4,height=4,framerate=5/1", bufs)
        assert r.error is None, r.error_text
        assert len(r.samples) == 3
        warns = [m for m in r.messages if m.type == m.type.WARNING]
        texts = [(m.src.get_name(), m.parse_warning()[0].message) for m in warns]
        assert len(texts) == 1, (run, texts)
        assert texts[0][0].startswith("nrreconstruct") and "no pixel is known" in texts[0][1]
    for _ in range(2):
        with pytest.warns(Warning, match="no pixel is known"):
            reconstruction.reconstruct(v, np.zeros((4, 4), bool), method="nearest")
