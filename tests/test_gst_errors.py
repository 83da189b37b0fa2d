"""Bad input gives a clear element error naming the element and the problem, and a non-zero exit from
gst-launch-1.0: never a crash, a hang or silent garbage. Runs that fail before preroll (not-negotiated) go
in-process with a bus wait that has a timeout: plain gst-launch-1.0 1.22 sometimes hangs on them."""
from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from conftest import hdr_buffer, run_appsrc
from test_element_properties import run_app, run_inprocess

pytestmark = pytest.mark.gst


def launch(env, *pipeline, timeout=60):
    p = subprocess.run(["gst-launch-1.0", "-e", *[str(x) for x in pipeline]], env=env, capture_output=True,
                       text=True, timeout=timeout)
    return p.returncode, p.stdout + p.stderr


def src(d, w=64, h=48, fmt="gray16-le", raw="clip.raw"):
    return ["filesrc", f"location={d / raw}", "!", "rawvideoparse", f"format={fmt}", f"width={w}",
            f"height={h}", "framerate=5/1", "!"]


def assert_element_error(rc, out, element, *needles):
    assert rc != 0, out
    lines = [ln for ln in out.splitlines() if ln.startswith("ERROR: from element") and f"{element}:" in ln]
    assert lines, f"no error from {element}:\n{out}"
    first = lines[0]
    for n in needles:
        assert n in first, f"{n!r} not in {first!r}"
    assert "Traceback" not in out, out


def inprocess_error(gst, desc, timeout=60.0):
    """(factory, error text) of the first error of `desc` run in this process (bus wait with a timeout)."""
    ok, err = run_inprocess(gst, desc, timeout)
    assert not ok, f"EOS instead of an error: {desc}"
    return err[0], err[2]


@pytest.mark.parametrize("run", range(20))
def test_gray8_into_nrvalidity(gst, tiny_clip, run):
    d, prof, _ = tiny_clip
    name, text = inprocess_error(gst, " ".join(src(d, fmt="gray8") + ["nrvalidity",
                                                                     f"profile={d / 'camera.json'}", "!",
                                                                     "fakesink"]))
    assert name == "nrvalidity"
    assert "needs raw GRAY16_LE sensor frames" in text and "got GRAY8 64x48" in text


def test_frame_size_differs_from_profile(gst, tiny_clip):
    d, prof, _ = tiny_clip
    name, text = inprocess_error(gst, " ".join(src(d, w=32, h=24) + ["nrvalidity",
                                                                    f"profile={d / 'camera.json'}", "!",
                                                                    "fakesink"]))
    assert name == "nrvalidity"
    assert "profile camera.json has a 64x48 mask but the stream is 32x24" in text


def test_missing_profile(gst_subprocess_env, tiny_clip, tmp_path):
    d, prof, _ = tiny_clip
    rc, out = launch(gst_subprocess_env, *src(d), "nrvalidity", f"profile={tmp_path / 'nope.json'}", "!",
                     "fakesink")
    assert_element_error(rc, out, "nrvalidity0", f"{tmp_path / 'nope.json'}: camera profile not found")
    rc, out = launch(gst_subprocess_env, *src(d), "nrvalidity", "!", "fakesink")
    assert_element_error(rc, out, "nrvalidity0", "no camera profile set (property 'profile' is empty)")


@pytest.mark.parametrize("case", ["json", "field", "mask"])
def test_corrupt_profile(gst_subprocess_env, tiny_clip, tmp_path, case):
    d, prof, _ = tiny_clip
    doc = json.loads((d / "camera.json").read_text())
    (tmp_path / "camera_mask.png").write_bytes((d / "camera_mask.png").read_bytes())
    p = tmp_path / "camera.json"
    if case == "json":
        p.write_text((d / "camera.json").read_text()[:40])
        needle = "not a valid JSON camera profile"
    elif case == "field":
        doc["nd"] = -2
        p.write_text(json.dumps(doc))
        needle = "field 'nd'"
    else:
        (tmp_path / "camera_mask.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
        p.write_text(json.dumps(doc))
        needle = "field 'mask'"
    rc, out = launch(gst_subprocess_env, *src(d), "nrvalidity", f"profile={p}", "!", "fakesink")
    assert_element_error(rc, out, "nrvalidity0", str(p), needle)


@pytest.mark.parametrize("between", [[], ["queue", "!"]])
def test_truncated_last_frame(gst_subprocess_env, tiny_clip, tmp_path, between):
    """rawvideoparse drops a partial last frame silently (GST_DEBUG only); nrvalidity asks upstream for the
    byte size (filesrc answers) and refuses a file that is not a whole number of frames."""
    d, prof, _ = tiny_clip
    data = (d / "clip.raw").read_bytes()
    cut = tmp_path / "cut.raw"
    cut.write_bytes(data[:30000])
    rc, out = run_app(gst_subprocess_env, " ".join(src(tmp_path, raw="cut.raw") + between + [
        "nrvalidity", f"profile={d / 'camera.json'}", "!", "fakesink"]))
    assert rc != 0, out
    line = next(ln for ln in out.splitlines() if ln.startswith("ERROR from nrvalidity0"))
    for needle in (f"{cut} is 30000 bytes", "truncated",
                   "not a whole number of 6144-byte 64x48 GRAY16_LE frames (4 frames + 5424 bytes)"):
        assert needle in line, line


def test_whole_frames_pass_the_size_check(gst_subprocess_env, tiny_clip):
    d, prof, raws = tiny_clip
    rc, out = launch(gst_subprocess_env, *src(d), "nrvalidity", f"profile={d / 'camera.json'}", "!",
                     "fakesink")
    assert rc == 0, out


def test_invalid_property_value(gst_subprocess_env, tiny_clip):
    """Choices are enums: gst-launch refuses an unknown word naming the property, the element and the
    value; a number out of range fails the start with an element error naming the property and range."""
    d, prof, _ = tiny_clip
    rc, out = launch(gst_subprocess_env, *src(d), "nrvalidity", f"profile={d / 'camera.json'}", "mode=bogus",
                     "!", "fakesink")
    assert rc != 0 and 'could not set property "mode" in element "nrvalidity" to "bogus"' in out, out
    rc, out = launch(gst_subprocess_env, *src(d), "nrvalidity", f"profile={d / 'camera.json'}", "!",
                     "nrreconstruct", "noise-fusion=exact", "!", "fakesink")
    assert rc != 0 and 'could not set property "noise-fusion" in element "nrreconstruct"' in out, out
    rc, out = launch(gst_subprocess_env, *src(d), "nrvalidity", f"profile={d / 'camera.json'}", "l-min=-7",
                     "!", "fakesink")
    assert_element_error(rc, out, "nrvalidity0", "property 'l-min' is out of range (-1 .. 65535)")
    rc, out = launch(gst_subprocess_env, *src(d), "nrvalidity", f"profile={d / 'camera.json'}", "!",
                     "nrtonemap", "smoothing=0", "!", "fakesink")
    assert_element_error(rc, out, "nrtonemap0", "value 0", "property 'smoothing' is out of range (0.001 .. 1)")


def test_exr_write_failure_names_file(gst_subprocess_env, tiny_clip, tmp_path):
    d, prof, _ = tiny_clip
    blocker = tmp_path / "blocker"
    blocker.write_text("not a folder")
    rc, out = launch(gst_subprocess_env, *src(d), "nrvalidity", f"profile={d / 'camera.json'}", "!",
                     "nrexrsink", f"location={blocker}/f_%03d.exr")
    assert_element_error(rc, out, "nrexrsink0", f"could not write {blocker}/f_000.exr")
    rc, out = launch(gst_subprocess_env, *src(d), "nrvalidity", f"profile={d / 'camera.json'}", "!",
                     "nrexrsink", f"location={tmp_path}/same.exr")
    assert_element_error(rc, out, "nrexrsink0", "has no %d", "frame 1 would overwrite frame 0")


def test_unlinkable_caps_are_refused_at_parse_time(gst_subprocess_env, tiny_clip):
    d, prof, _ = tiny_clip
    rc, out = launch(gst_subprocess_env, "videotestsrc", "num-buffers=2", "!",
                     "video/x-raw,format=GRAY8,width=64,height=48", "!", "nrvalidity",
                     f"profile={d / 'camera.json'}", "!", "fakesink")
    assert rc != 0
    assert "could not link" in out and "nrvalidity0" in out


# ---- in-process: exceptions and missing context become element errors ----------------------------------

def test_exception_in_transform_is_an_element_error(gst, tiny_clip, monkeypatch):
    from conftest import raw_buffer
    from nrhdr_core import validity
    d, prof, raws = tiny_clip

    def before(i, pipeline):
        if i == 1:
            monkeypatch.setattr(validity, "classify", lambda *a, **k: 1 / 0)

    r = run_appsrc(f"nrvalidity profile={d / 'camera.json'}",
                   f"video/x-raw,format=GRAY16_LE,width={prof.width},height={prof.height},framerate=5/1",
                   [raw_buffer(x, pts=i * 200_000_000, duration=200_000_000) for i, x in enumerate(raws)],
                   before_push=before, lockstep=True)
    assert r.error is not None
    assert r.error[0] == "nrvalidity0" or r.error[0].startswith("nrvalidity")
    assert "frame 1: ZeroDivisionError" in r.error[1]
    assert len(r.samples) == 1            # frame 0 only: nothing from or after the failing frame


def test_crosstalk_without_any_profile(gst):
    v = np.ones((4, 4), np.float32)
    s = np.zeros((4, 4), np.uint8)
    r = run_appsrc("nrcrosstalk", "other/x-nrhdr,width=4,height=4,framerate=5/1",
                   [hdr_buffer(v, s, pts=0, duration=1)])
    assert r.error is not None and r.error[0].startswith("nrcrosstalk")
    assert "no camera profile" in r.error[1]


def test_hdr_buffer_with_wrong_layout(gst):
    """A buffer that is not 5*W*H bytes (f32-u8-planar) for the caps' size is refused, not misread."""
    from gi.repository import Gst
    buf = Gst.Buffer.new_wrapped(bytes(4 * 16 + 15))           # one byte short
    buf.pts, buf.duration = 0, 1
    r = run_appsrc("nrreconstruct method=preview", "other/x-nrhdr,width=4,height=4,framerate=5/1", [buf])
    assert r.error is not None and r.error[0].startswith("nrreconstruct")
    assert "not an nrhdr HDR frame" in r.error[1] and "79 bytes" in r.error[1] and "expected 80 bytes" in r.error[1]


def test_hdr_caps_with_an_unknown_layout(gst):
    v = np.ones((4, 4), np.float32)
    s = np.zeros((4, 4), np.uint8)
    r = run_appsrc("nrreconstruct method=preview",
                   "other/x-nrhdr,layout=(string)f16-packed,width=4,height=4,framerate=5/1",
                   [hdr_buffer(v, s, pts=0, duration=1)])
    assert r.error is not None and r.error[0].startswith("nrreconstruct")
    assert "layout 'f16-packed' is not supported" in r.error[1]
