"""Raw still sequences (16-bit gray TIFF / PNG, one frame per file): `io.still_sequence` and the source
element `nrimagesrc` (docs/ELEMENTS.md). The sequences are written here from a simulated clip's raw frames;
through the chain they must give what the raw clip gives (filesrc ! rawvideoparse), with the count and the
timestamps of the frame rate; every bad input is an error naming the element's property and the file."""
from __future__ import annotations

import os

import numpy as np
import pytest

from conftest import make_test_clip

CHAIN = "nrvalidity profile={p} ! nrcrosstalk ! nrreconstruct method=fse preset=fast"


def write_stills(folder, frames, pattern="frame_{:05d}.tif", first=0, dtype=np.uint16):
    from nrhdr_core import io
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        io.write_image(folder / pattern.format(first + i), np.asarray(f), dtype)
    return folder


@pytest.fixture(scope="module")
def clip4(tmp_path_factory):
    """A 64x48 clip of 4 frames (dark, valid and clipped pixels of both kinds) and its frames as a TIFF
    folder (frame_00000.tif ...) and a PNG folder numbered from 1 without padding (shot1.png ... shot4.png,
    natural order)."""
    base = tmp_path_factory.mktemp("stills")
    d, prof, raws = make_test_clip(base / "clip", frames=4)
    tif = write_stills(base / "tif", raws)
    png = write_stills(base / "png", raws, "shot{}.png", first=1)
    return d, prof, raws, tif, png


def run_source(desc, timeout=120.0):
    """`desc ! appsink`: (samples [(pts, duration, offset, payload)], first error text or None)."""
    import time
    from gi.repository import Gst
    from conftest import sample_payload
    pipeline = Gst.parse_launch(f"{desc} ! appsink name=sink sync=false")
    sink, bus = pipeline.get_by_name("sink"), pipeline.get_bus()
    out, error = [], None
    try:
        pipeline.set_state(Gst.State.PLAYING)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = bus.pop_filtered(Gst.MessageType.ERROR)
            if m is not None:
                err, _ = m.parse_error()
                error = f"{m.src.get_name()}: {err.message}"
                break
            smp = sink.try_pull_sample(50 * Gst.MSECOND)
            if smp is not None:
                b = smp.get_buffer()
                out.append((b.pts, b.duration, b.offset, sample_payload(smp)))
            elif sink.is_eos():       # a source's flow error is followed by EOS: its message may come later
                m = bus.timed_pop_filtered(200 * Gst.MSECOND, Gst.MessageType.ERROR)
                if m is not None:
                    error = f"{m.src.get_name()}: {m.parse_error()[0].message}"
                break
        else:
            raise AssertionError(f"{desc}: no EOS within {timeout} s")
    finally:
        pipeline.set_state(Gst.State.NULL)
    return out, error


# ---- io.still_sequence -----------------------------------------------------------------------------------

def test_still_sequence_reads_the_codes_in_frame_order(clip4, tmp_path):
    from nrhdr_core import io
    _, _, raws, tif, png = clip4
    for loc in (tif, png, tif / "frame_%05d.tif", png / "shot%d.png"):
        seq = io.still_sequence(loc)
        assert (len(seq), seq.height, seq.width) == raws.shape
        for i in range(len(seq)):
            got = seq.read(i)
            assert got.dtype == np.uint16 and np.array_equal(got, raws[i]), (loc, i)
    assert [os.path.basename(f) for f in io.still_sequence(png).files] == [f"shot{i}.png" for i in (1, 2, 3, 4)]
    assert len(io.still_sequence(tif / "frame_%05d.tif", start_index=2)) == 2
    # every code of the 16-bit range survives, in both formats
    full = np.arange(1 << 16, dtype=np.uint16).reshape(256, 256)
    for ext in ("tif", "png"):
        d = write_stills(tmp_path / ext, [full, full[::-1]], "f{}." + ext)
        seq = io.still_sequence(d)
        assert np.array_equal(seq.read(0), full) and np.array_equal(seq.read(1), full[::-1])
    # other files, hidden files and the mask of the folder's camera profile are not frames
    import shutil
    d = clip4[0]
    (png / "notes.txt").write_text("camera settings")
    (png / ".shot9.png").write_bytes(b"")
    for f in ("camera.json", "camera_mask.png"):
        shutil.copy(d / f, png / f)
    assert [os.path.basename(f) for f in io.still_sequence(png).files] == [f"shot{i}.png" for i in (1, 2, 3, 4)]
    for f in ("notes.txt", ".shot9.png", "camera.json", "camera_mask.png"):
        (png / f).unlink()


def _bad(tmp_path, raws, case):
    """(location, text the error must hold[, start-index]) of a broken sequence."""
    from nrhdr_core import io
    d = tmp_path / case
    d.mkdir()
    small = raws[0][:40, :60]
    if case == "mixed-sizes":
        write_stills(d, [raws[0], raws[1], small])
        return d, ["frame_00002.tif", "image is 60x40, expected 64x48", "size of the first"]
    if case == "8-bit":
        write_stills(d, [raws[0] >> 8, raws[1] >> 8], dtype=np.uint8)
        return d, ["frame_00000.tif", "8-bit", "16-bit"]
    if case == "rgb":
        write_stills(d, [np.stack([raws[0]] * 3, -1)])
        return d, ["frame_00000.tif", "3 channels", "one gray channel"]
    if case == "gray-alpha":
        write_stills(d, [np.stack([raws[0]] * 2, -1)], "frame_{:05d}.png")
        return d, ["frame_00000.png", "2 channels"]
    if case == "float":
        write_stills(d, [raws[0].astype(np.float32)], dtype=np.float32)
        return d, ["frame_00000.tif", "pixel type float", "unsigned 16-bit"]
    if case == "12-bit-samples":
        io.write_image(d / "frame_00000.tif", raws[0], np.uint16, attributes={"oiio:BitsPerSample": 12})
        return d, ["frame_00000.tif", "12 bits per sample"]
    if case == "missing-in-folder":
        write_stills(d, raws)
        (d / "frame_00002.tif").unlink()
        return d, [str(d), "1 frame(s) missing between frame_00001.tif and frame_00003.tif"]
    if case == "missing-in-pattern":
        write_stills(d, raws)
        (d / "frame_00001.tif").unlink()
        return d / "frame_%05d.tif", ["frame_00001.tif: missing", "frames 0..0", "2 more from index 2"]
    if case == "empty-folder":
        return d, [str(d), "no still images"]
    if case == "not-an-image":
        write_stills(d, raws[:2])
        (d / "frame_00002.tif").write_text("this is not a TIFF\n")
        return d, ["frame_00002.tif", "cannot read image"]
    if case == "truncated":
        write_stills(d, raws[:3])
        data = (d / "frame_00001.tif").read_bytes()
        (d / "frame_00001.tif").write_bytes(data[:len(data) // 2])
        return d, ["frame_00001.tif"]
    if case == "mixed-extensions":
        write_stills(d, raws[:2])
        write_stills(d, raws[2:], "frame_{:05d}.png", first=2)
        return d, [str(d), "holds 2 .png, 2 .tif files", "one kind"]
    if case == "link-out-of-folder":
        outside = write_stills(tmp_path / "elsewhere", raws[:1], "secret.tif")
        write_stills(d, raws[:2])
        os.symlink(outside / "secret.tif", d / "frame_00002.tif")
        return d, ["frame_00002.tif", "is a link out of the folder", "allow-outside-paths"]
    if case == "pattern-start-missing":
        write_stills(d, raws, first=1)
        return d / "frame_%05d.tif", ["frame_00000.tif: no such file", "start-index 0", "start at index 1"], 0
    if case == "two-pages":
        import OpenImageIO as oiio
        spec = oiio.ImageSpec(raws.shape[2], raws.shape[1], 1, oiio.UINT16)
        out = oiio.ImageOutput.create(str(d / "frame_00000.tif"))
        assert out.open(str(d / "frame_00000.tif"), [spec, spec])
        out.write_image(np.ascontiguousarray(raws[0][:, :, None]))
        out.open(str(d / "frame_00000.tif"), spec, "AppendSubimage")
        out.write_image(np.ascontiguousarray(raws[1][:, :, None]))
        out.close()
        return d, ["frame_00000.tif", "more than one image"]
    raise AssertionError(case)


BAD = ["mixed-sizes", "8-bit", "rgb", "gray-alpha", "float", "12-bit-samples", "missing-in-folder",
       "missing-in-pattern", "empty-folder", "not-an-image", "truncated", "mixed-extensions",
       "link-out-of-folder", "pattern-start-missing", "two-pages"]


@pytest.mark.gst
@pytest.mark.parametrize("case", BAD)
def test_bad_sequences_are_errors_naming_the_file(clip4, tmp_path, case, gst):
    """io.still_sequence refuses the sequence before any frame is used, and nrimagesrc fails to start with
    an element error naming `location`, the file and what is wrong; no frame is pushed."""
    from nrhdr_core import io
    _, _, raws, _, _ = clip4
    loc, words, *start = _bad(tmp_path, raws, case)
    start = start[0] if start else -1
    if case == "truncated":     # the header is whole: refused when its pixels are decoded
        seq = io.still_sequence(loc)
        with pytest.raises(io.ImageFileError, match="frame_00001.tif: cannot decode pixels"):
            seq.read(1)
    else:
        with pytest.raises(io.ImageFileError) as e:
            io.still_sequence(loc, start)
        for w in words:
            assert w in str(e.value), (case, w, str(e.value))
    samples, error = run_source(f"nrimagesrc location={loc} start-index={start}")
    assert error is not None and error.startswith("nrimagesrc"), (case, error)
    assert f"location={loc}: " in error, error
    for w in words:
        assert w in error, (case, w, error)
    if case == "truncated":
        assert [s[2] for s in samples] == [0] and "frame 1:" in error     # frame 0 went out, then the error
    else:
        assert samples == []
    if case == "link-out-of-folder":       # trusted: the property lets it through
        samples, error = run_source(f"nrimagesrc location={loc} allow-outside-paths=true")
        assert error is None and len(samples) == 3


def test_a_file_removed_after_the_check_fails_when_read(clip4, tmp_path):
    from nrhdr_core import io
    _, _, raws, _, _ = clip4
    d = write_stills(tmp_path / "s", raws)
    seq = io.still_sequence(d)
    (d / "frame_00002.tif").unlink()
    assert np.array_equal(seq.read(1), raws[1])
    with pytest.raises(io.ImageFileError, match="frame_00002.tif: no such file"):
        seq.read(2)


# ---- nrimagesrc --------------------------------------------------------------------------------------------

@pytest.mark.gst
def test_nrimagesrc_frames_timestamps_and_count(clip4, gst):
    """Frames out = files in, as written; PTS = i / framerate (exact for 30000/1001), durations to the
    next PTS, offsets i; caps GRAY16_LE at the files' size and the frame rate."""
    _, _, raws, tif, png = clip4
    for loc in (tif, png, tif / "frame_%05d.tif"):
        samples, error = run_source(f"nrimagesrc location={loc} framerate=30000/1001")
        assert error is None, error
        assert len(samples) == len(raws)
        for i, (pts, dur, off, frame) in enumerate(samples):
            assert pts == i * 1001 * gst.SECOND // 30000 and off == i
            assert pts + dur == (i + 1) * 1001 * gst.SECOND // 30000
            assert np.array_equal(frame, raws[i])
    el = gst.ElementFactory.make("nrimagesrc", None)
    assert el.get_property("frames") == 0 and el.get_property("framerate") == "30/1"


@pytest.mark.gst
def test_nrimagesrc_start_index_and_loop(clip4, gst):
    _, _, raws, tif, _ = clip4
    samples, error = run_source(f"nrimagesrc location={tif}/frame_%05d.tif start-index=1 loop=true "
                                f"framerate=10 num-buffers=7")
    assert error is None, error
    assert [s[0] for s in samples] == [i * gst.SECOND // 10 for i in range(7)]
    for i, s in enumerate(samples):
        assert np.array_equal(s[3], raws[1 + i % 3]), i


@pytest.mark.gst
@pytest.mark.parametrize("bad", ["abc", "0/1", "30/0", "-5", "1000001/1"])
def test_nrimagesrc_refuses_a_bad_framerate(clip4, gst, bad):
    _, _, _, tif, _ = clip4
    samples, error = run_source(f"nrimagesrc location={tif} framerate={bad}")
    assert samples == [] and error is not None and f"framerate={bad}: " in error, error


@pytest.mark.gst
def test_nrimagesrc_start_index_is_for_patterns(clip4, gst):
    _, _, _, tif, _ = clip4
    samples, error = run_source(f"nrimagesrc location={tif} start-index=2")
    assert samples == [] and "start-index 2 is for a file pattern" in error, error
    samples, error = run_source("nrimagesrc")
    assert samples == [] and "location is empty" in error, error


@pytest.mark.gst
@pytest.mark.parametrize("fmt", ["tif", "png"])
def test_stills_through_the_chain_equal_the_raw_clip(clip4, gst, fmt):
    """nrimagesrc ! chain gives, frame by frame, the values and states (float32 bits) of filesrc !
    rawvideoparse ! chain over the same frames as a raw clip, with the same timestamps."""
    d, prof, raws, tif, png = clip4
    h, w = raws.shape[1:]
    chain = CHAIN.format(p=d / "camera.json")
    got, error = run_source(f"nrimagesrc location={tif if fmt == 'tif' else png} framerate=5/1 ! {chain}")
    assert error is None, error
    want, error = run_source(f"filesrc location={d / 'clip.raw'} ! rawvideoparse format=gray16-le width={w} "
                             f"height={h} framerate=5/1 plane-strides=<{2 * w}> ! {chain}")
    assert error is None, error
    assert len(got) == len(want) == len(raws)
    for (pa, da, _, (va, sa)), (pb, db, _, (vb, sb)) in zip(got, want):
        assert (pa, da) == (pb, db)
        assert np.array_equal(sa, sb)
        assert np.array_equal(va.view(np.uint32), vb.view(np.uint32))
    from nrhdr_core import states
    assert all(0 < ((s[3][1] & states.RECONSTRUCTED) != 0).mean() < 1 for s in got)


@pytest.mark.gst
def test_odd_width_frames_fill_the_padded_rows(tmp_path, gst):
    """GStreamer pads GRAY16_LE rows of an odd width to 4 bytes: the frame is written at the caps' stride."""
    frames = np.arange(2 * 5 * 7, dtype=np.uint16).reshape(2, 5, 7) * 900
    d = write_stills(tmp_path / "odd", frames, "f{}.png")
    samples, error = run_source(f"nrimagesrc location={d}")
    assert error is None, error
    assert [np.array_equal(s[3], f) for s, f in zip(samples, frames)] == [True, True]


def test_fuzz_locations_are_a_sequence_or_an_error_naming_them(tmp_path):
    """Any location text (patterns with stray or several conversions, numbering gaps, names out of order)
    over a folder of numbered stills gives a checked sequence of consecutive files in that folder, or an
    ImageFileError; never another exception."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
    from nrhdr_core import io
    d = tmp_path / "s"
    frame = np.arange(12, dtype=np.uint16).reshape(3, 4)
    for name in ("f_1.tif", "f_2.tif", "f_03.tif", "f_10.tif", "g%1.png", "g%2.png", "h0001.tif"):
        write_stills(d, [frame], name)
    fuzz = settings(max_examples=int(os.environ.get("NRHDR_FUZZ_EXAMPLES", "0") or 0) or 60, deadline=None,
                    derandomize=not os.environ.get("NRHDR_FUZZ_EXAMPLES"), database=None,
                    suppress_health_check=list(HealthCheck))

    @fuzz
    @given(text=st.text(st.sampled_from("fgh_%01234d.tifpng"), max_size=14), start=st.integers(-1, 12))
    def run(text, start):
        try:
            seq = io.still_sequence(d / text, start)
        except io.ImageFileError as e:
            assert str(e)
            return
        assert len(seq) >= 1 and all(os.path.dirname(f) == str(d) for f in seq.files)
        assert np.array_equal(seq.read(0), frame)
    run()
    assert len(io.still_sequence(d / "h%04d.tif")) == 1 and len(io.still_sequence(d / "g%%%d.png")) == 2
    with pytest.raises(io.ImageFileError, match=r"f_3.tif: missing: the sequence has frames 1..2 and 1 more"):
        io.still_sequence(d / "f_%d.tif")          # f_1, f_2, f_10 (f_03 is not f_3)
