"""Property-based fuzzing (hypothesis) of every reader (docs/RELIABILITY.md): camera profiles (JSON, mask
image), crosstalk calibrations (entry, arrays, file), clip.json, JSON nesting, image files (PNG headers of
any size, truncated and corrupted PNG/TIFF/EXR), scenes, command-line numbers, the flat-field index
(exposures.csv) and flat frames, raw video files and the raw-frame path. Every input either works or fails
with the module's own error type (ProfileError, CalibrationError, ClipError, ImageFileError,
validity.FrameError, ValueError for reconstruction) naming the file, never another exception and never a
huge allocation."""
from __future__ import annotations

import json
import os
import shutil
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from nrhdr_core import calibration, crosstalk, io, profile, reconstruction, simulate, tonemap, validity

# Bounded for the suite (seconds, reproducible); NRHDR_FUZZ_EXAMPLES=2000 for a deeper, random run.
_DEEP = int(os.environ.get("NRHDR_FUZZ_EXAMPLES", "0") or 0)
FUZZ = settings(max_examples=_DEEP or 60, deadline=None, derandomize=not _DEEP, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

H, W = 12, 16

# JSON-like values of every kind, including the ones that broke readers before (NaN, huge, strings)
scalars = st.one_of(st.none(), st.booleans(), st.integers(-2 ** 70, 2 ** 70),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
                    st.sampled_from([0, 1, -1, 16, 12, "12", "16", 1e308, 1e-308, 4094, 65535, 1e6, 2 ** 31]))
json_values = st.recursive(scalars, lambda c: st.one_of(st.lists(c, max_size=3),
                                                         st.dictionaries(st.text(max_size=6), c, max_size=3)),
                           max_leaves=6)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A valid profile with a (identity) crosstalk calibration; the fuzzers mutate copies of it."""
    d = tmp_path_factory.mktemp("fuzz_base")
    p = profile.default(H, W, seed=2)
    p = p.replace(crosstalk=crosstalk.identity_calibration(p.mask))
    profile.save(p, d / "cam.json")
    return d


def _copy(base: Path, tmp: Path) -> Path:
    if tmp.exists():
        shutil.rmtree(tmp)
    shutil.copytree(base, tmp)
    return tmp / "cam.json"


def _load_or_profile_error(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", profile.ProfileWarning)
        try:
            p = profile.load(path)
        except profile.ProfileError:
            return None
    # whatever loads must be usable downstream: a finite white and a frame that classifies
    assert np.isfinite(p.white) and p.white > 0
    raw = np.full(p.mask.shape, min(p.clip_code, 65535), np.uint16)
    v, s = validity.classify(raw, p)
    assert np.isfinite(v).all()
    return p


# ---- profiles ---------------------------------------------------------------------------------------------

FIELDS = ["format", "version", "width", "height", "mask", "nd", "bit_depth", "clip_code", "black_level", "gain",
          "read_noise", "full_well", "l_min", "name", "crosstalk", "extra"]


@FUZZ
@given(changes=st.dictionaries(st.sampled_from(FIELDS + ["other"]), json_values, min_size=1, max_size=4),
       drop=st.lists(st.sampled_from(FIELDS), max_size=2))
def test_fuzz_profile_fields(base, tmp_path, changes, drop):
    f = _copy(base, tmp_path / "p")
    doc = json.loads(f.read_text())
    doc.update(changes)
    for k in drop:
        doc.pop(k, None)
    f.write_text(json.dumps(doc))      # NaN / Infinity are written as JSON extensions: the reader must cope
    _load_or_profile_error(f)


@FUZZ
@given(data=st.binary(max_size=300), cut=st.integers(0, 2000))
def test_fuzz_profile_bytes(base, tmp_path, data, cut):
    f = _copy(base, tmp_path / "p")
    text = f.read_bytes()
    f.write_bytes(text[:cut] + data)   # truncated JSON with garbage after it
    _load_or_profile_error(f)


@FUZZ
@given(shape=st.tuples(st.integers(1, 20), st.integers(1, 20)), channels=st.sampled_from([1, 2, 3, 4]),
       dtype=st.sampled_from([np.uint8, np.uint16, np.float32]), values=st.sampled_from(["binary", "random"]),
       seed=st.integers(0, 2 ** 16))
def test_fuzz_profile_mask_image(base, tmp_path, shape, channels, dtype, values, seed):
    f = _copy(base, tmp_path / "p")
    rng = np.random.default_rng(seed)
    full = 1.0 if dtype == np.float32 else np.iinfo(dtype).max
    img = rng.integers(0, 2, shape + (channels,)) * full if values == "binary" else \
        rng.random(shape + (channels,)) * full
    io.write_image(f.parent / "cam_mask.png", img.astype(dtype) if dtype != np.float32 else
                   (img * 65535).astype(np.uint16), dtype if dtype != np.float32 else np.uint16)
    _load_or_profile_error(f)


# ---- crosstalk calibrations (the .npz and the profile's entry) ---------------------------------------------

ENTRY = ["format", "version", "file", "width", "height", "knots", "qscale", "qoffset", "nd", "black_level",
         "clip_code", "info", "mask_sha256", "mask_width", "mask_height", "bit_depth"]


@FUZZ
@given(changes=st.dictionaries(st.sampled_from(ENTRY), json_values, min_size=1, max_size=3))
def test_fuzz_calibration_entry(base, tmp_path, changes):
    f = _copy(base, tmp_path / "p")
    doc = json.loads(f.read_text())
    doc["crosstalk"].update(changes)
    f.write_text(json.dumps(doc))
    _load_or_profile_error(f)


ARRAYS = ["codes_q", "n_knots", "knot_flux", "clip_flux", "sig_e", "sigma", "alpha"]


@FUZZ
@given(name=st.sampled_from(ARRAYS), shape=st.lists(st.integers(0, 17), min_size=0, max_size=3),
       dtype=st.sampled_from([np.uint8, np.uint16, np.int32, np.float16, np.float32, np.float64]),
       fill=st.sampled_from([0.0, 1.0, -1.0, np.nan, np.inf, 300.0, 1e30]), drop=st.booleans())
def test_fuzz_calibration_arrays(base, tmp_path, name, shape, dtype, fill, drop):
    f = _copy(base, tmp_path / "p")
    npz = f.parent / "cam_crosstalk.npz"
    with np.load(npz) as z:
        arrs = {k: z[k] for k in z.files}
    if drop:
        del arrs[name]
    else:
        with np.errstate(invalid="ignore", over="ignore"):
            arrs[name] = np.full(tuple(shape), fill).astype(dtype)
    np.savez(npz, **arrs)
    p = _load_or_profile_error(f)
    if p is not None and p.crosstalk is not None:   # a calibration that loads must also correct a frame
        raw = np.random.default_rng(0).integers(0, 4096, p.mask.shape).astype(np.uint16)
        v, s = validity.classify(raw, p)
        crosstalk.correct(v, s, p, mode="lut")
        crosstalk.correct(v, s, p, mode="kernel")


@FUZZ
@given(cut=st.integers(0, 5000), junk=st.binary(max_size=64))
def test_fuzz_calibration_file_truncated(base, tmp_path, cut, junk):
    f = _copy(base, tmp_path / "p")
    npz = f.parent / "cam_crosstalk.npz"
    b = npz.read_bytes()
    assume(cut < len(b) or junk)
    npz.write_bytes(b[:cut] + junk)
    _load_or_profile_error(f)


# ---- flat-field index (exposures.csv) and flat frames --------------------------------------------------------

csv_cell = st.one_of(st.sampled_from(["flat_000_00.tif", "flat_001_00.tif", "flat_001_01.tif", "missing.tif",
                                      "0", "0.01", "-1", "nan", "inf", "1e400", "", " ", "x,y", '"q"',
                                      "file", "exposure_s", "\x00", "../flat_000_00.tif"]),
                     st.text(max_size=6))


@FUZZ
@given(header=st.lists(st.sampled_from(["file", "exposure_s", "extra", "", "File"]), min_size=0, max_size=3),
       rows=st.lists(st.lists(csv_cell, min_size=0, max_size=4), max_size=8), bom=st.booleans())
def test_fuzz_flats_index(tmp_path, header, rows, bom):
    d = tmp_path / "flats"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir()
    for n in ("flat_000_00.tif", "flat_001_00.tif", "flat_001_01.tif"):
        io.write_image(d / n, np.zeros((4, 5), np.uint16), np.uint16)
    text = "\n".join(",".join(r) for r in [header] + rows) + "\n"
    (d / "exposures.csv").write_text(("\ufeff" if bom else "") + text, encoding="utf-8")
    try:
        index = calibration.read_index(d)
    except calibration.CalibrationError:
        return
    assert all(np.isfinite(t) and t >= 0 and len(g) >= 2 for t, g in index)


@FUZZ
@given(shapes=st.lists(st.sampled_from([(4, 5), (5, 4), (4, 5, 3), (1, 1)]), min_size=6, max_size=6),
       dtype=st.sampled_from([np.uint8, np.uint16, np.float32]), corrupt=st.integers(-1, 5))
def test_fuzz_flat_frames(tmp_path, shapes, dtype, corrupt):
    d = tmp_path / "flats"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir()
    rows = ["file,exposure_s"]
    for i, shp in enumerate(shapes):
        n = f"flat_{i // 2:03d}_{i % 2:02d}.tif"
        io.write_image(d / n, np.full(shp, i * 10).astype(dtype), dtype)
        if i == corrupt:
            (d / n).write_bytes((d / n).read_bytes()[:20])     # truncated TIFF
        rows.append(f"{n},{0.01 * (i // 2)}")
    (d / "exposures.csv").write_text("\n".join(rows) + "\n")
    try:
        sweep = calibration.read_flats(d, progress=False)
    except calibration.CalibrationError:
        return
    assert sweep.mean.shape[0] == 3 and np.isfinite(sweep.mean).all()


# ---- clip.json, JSON nesting ---------------------------------------------------------------------------------

CLIP_FIELDS = ["format", "version", "width", "height", "fps", "frames", "raw", "profile", "truth", "pixel_format"]
names = st.one_of(st.sampled_from(["clip.raw", "camera.json", "../clip.raw", "/etc/passwd", "sub/../clip.raw",
                                   "link_out", "link_in", "..", ".", "", "a\x00b", "truth/frame_%05d.exr"]),
                  st.text(max_size=8))


@pytest.fixture(scope="module")
def clip_base(tmp_path_factory):
    from conftest import make_test_clip
    d, _, _ = make_test_clip(tmp_path_factory.mktemp("fuzz_clip") / "clip", width=16, height=12, frames=2)
    return d


@FUZZ
@given(changes=st.dictionaries(st.sampled_from(CLIP_FIELDS), st.one_of(json_values, names), min_size=1, max_size=4))
def test_fuzz_clip_json(clip_base, tmp_path, changes):
    d = tmp_path / "c"
    if d.exists():
        shutil.rmtree(d)
    shutil.copytree(clip_base, d)
    os.symlink("/etc/passwd", d / "link_out")
    os.symlink("clip.raw", d / "link_in")
    doc = json.loads((d / "clip.json").read_text())
    doc.update(changes)
    (d / "clip.json").write_text(json.dumps(doc))
    try:
        info = simulate.load_clip(d)
    except simulate.ClipError as e:
        assert "clip.json" in str(e) or str(d) in str(e)
        return
    root = d.resolve()
    for k in simulate.CLIP_FILES:
        if f"{k}_path" in info:
            real = Path(info[f"{k}_path"]).resolve()
            assert real == root or root in real.parents
    assert all(isinstance(info[k], int) and info[k] >= 1 for k in ("width", "height", "fps", "frames"))


@FUZZ
@given(depth=st.integers(0, 20000), opener=st.sampled_from(["[", '{"a":', '{"mask": [']), cut=st.integers(0, 3),
       reader=st.sampled_from(["profile", "clip"]))
def test_fuzz_json_nesting(tmp_path, depth, opener, cut, reader):
    closer = {"[": "]", '{"a":': "}", '{"mask": [': "]}"}[opener]
    text = opener * depth + "1" + closer * max(depth - cut, 0)
    if reader == "profile":
        f = tmp_path / "cam.json"
        f.write_text(text)
        with pytest.raises(profile.ProfileError, match="cam.json"):
            profile.load(f)
    else:
        (tmp_path / "clip.json").write_text(text)
        with pytest.raises(simulate.ClipError, match="clip.json"):
            simulate.load_clip(tmp_path)


# ---- image files: headers of any size, truncated and corrupted files ------------------------------------------

def _png(width, height, bit_depth, colour, rows, pad):
    def chunk(kind, data):
        return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")
    ihdr = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([bit_depth, colour, 0, 0, 0])
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + (chunk(b"zpAd", bytes(pad)) if pad else b"")
            + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


dims = st.one_of(st.integers(1, 48), st.sampled_from([65535, 60000, 2 ** 31 - 1]))


@FUZZ
@given(w=dims, h=dims, bit_depth=st.sampled_from([1, 8, 16]), colour=st.sampled_from([0, 2, 4, 6]),
       rows=st.binary(max_size=400), pad=st.sampled_from([0, 2 << 20]), reader=st.sampled_from(["mask", "image"]))
def test_fuzz_png_headers(tmp_path, w, h, bit_depth, colour, rows, pad, reader):
    """A PNG declaring any size (up to 2^31 - 1 per side) with too little or garbage data: an array of the
    declared size or an ImageFileError naming the file, decided from the header for the huge ones."""
    f = tmp_path / "m.png"
    f.write_bytes(_png(w, h, bit_depth, colour, rows, pad))
    try:
        a = io.read_mask(f) if reader == "mask" else io.read_image(f, np.float32)
    except io.ImageFileError as e:
        assert str(f) in str(e)
        return
    assert w * h <= io.MAX_PIXELS and a.shape[:2] == (h, w)


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz_images")
    rng = np.random.default_rng(3)
    io.write_exr(d / "f.exr", (rng.random((20, 24)) * 1e4).astype(np.float32), rng.integers(0, 200, (20, 24)))
    io.write_image(d / "f.png", rng.integers(0, 65535, (20, 24)).astype(np.uint16), np.uint16)
    io.write_image(d / "f.tif", rng.integers(0, 65535, (20, 24)).astype(np.uint16), np.uint16)
    io.write_mask(d / "m.png", rng.random((20, 24)) < 0.5)
    return d


@FUZZ
@given(name=st.sampled_from(["f.exr", "f.png", "f.tif", "m.png"]), cut=st.integers(0, 4000),
       flips=st.lists(st.tuples(st.integers(0, 4000), st.integers(1, 255)), max_size=4),
       reader=st.sampled_from(["image", "exr", "mask", "luminance"]))
def test_fuzz_image_bytes(images, tmp_path, name, cut, flips, reader):
    """Truncated or corrupted images (header bytes included): the declared-size array or ImageFileError."""
    b = bytearray((images / name).read_bytes())
    for pos, x in flips:
        if pos < len(b):
            b[pos] ^= x
    f = tmp_path / name
    f.write_bytes(bytes(b[:cut]) if cut < len(b) else bytes(b))
    read = {"image": lambda: io.read_image(f, np.uint16), "exr": lambda: io.read_exr(f)[0],
            "mask": lambda: io.read_mask(f), "luminance": lambda: io.read_luminance(f)}[reader]
    try:
        a = read()
    except io.ImageFileError as e:
        assert str(f) in str(e)
        return
    assert a.shape[0] * a.shape[1] <= io.MAX_PIXELS
    if reader == "luminance":
        assert np.isfinite(a).all() and (a >= 0).all()


# ---- scenes and command-line numbers -------------------------------------------------------------------

@FUZZ
@given(value=st.floats(allow_nan=True, allow_infinity=True, width=32), other=st.floats(0, 1e4, width=32),
       stops=st.floats(-30, 30))
def test_fuzz_scene_values(value, other, stops):
    scene = np.full((6, 6), other, np.float32)
    scene[2:4, 1:5] = value
    prof = profile.default(4, 4)
    try:
        k = simulate.check_scene(scene, prof, stops)
    except ValueError as e:
        assert str(e).startswith("scene: ")
        return
    flux = simulate.view(scene, 4, 4, 0.5, simulate.Motion()) * np.float32(k)
    assert np.isfinite(flux).all() and flux.max() <= simulate.FLUX_MAX


@FUZZ
@given(text=st.one_of(st.text(max_size=12), st.sampled_from(["nan", "NaN", "inf", "-inf", "1e308", "1e309", "-0",
                                                            "0x10", "1_000", " 5", "5.0", "1e-320", "9" * 400])),
       lo=st.sampled_from([None, 0, 1, -30]), integer=st.booleans())
def test_fuzz_cli_number(text, lo, integer):
    import argparse
    from gst_plugins.cli.args import number
    parse = number(lo, 1000, integer=integer)
    try:
        v = parse(text)
    except argparse.ArgumentTypeError as e:
        assert repr(text) in str(e) or text in str(e)
        return
    assert np.isfinite(v) and (lo is None or v >= lo) and v <= 1000
    assert isinstance(v, int) if integer else isinstance(v, float)


# ---- raw video files and the raw-frame path ----------------------------------------------------------------

@FUZZ
@given(w=st.integers(-1, 9), h=st.integers(-1, 7), nbytes=st.integers(0, 700))
def test_fuzz_raw_video_file(tmp_path, w, h, nbytes):
    f = tmp_path / "clip.raw"
    f.write_bytes(bytes(range(256)) * (nbytes // 256) + bytes(nbytes % 256))
    try:
        v = io.read_raw_video(f, w, h)
    except io.ImageFileError:
        return
    assert v.shape[1:] == (h, w) and v.shape[0] * w * h * 2 == nbytes
    del v


@FUZZ
@given(shape=st.tuples(st.integers(1, 24), st.integers(1, 24)), seed=st.integers(0, 2 ** 16),
       codes=st.sampled_from(["any", "high", "low", "clip"]), mode=st.sampled_from(["threshold", "all", "best",
                                                                                     "bogus"]),
       l_min=st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)),
       method=st.sampled_from(["preview", "nearest", "linear"]))
def test_fuzz_raw_frame_path(shape, seed, codes, mode, l_min, method):
    """raw codes -> classify -> crosstalk -> reconstruct -> tone map, on random sizes and codes (also above the
    ADC range), random modes and l_min (NaN/Inf): works, or a FrameError/ValueError naming the problem."""
    rng = np.random.default_rng(seed)
    prof = profile.default(shape[0], shape[1], seed=seed % 7)
    hi = {"any": 65536, "high": 65536, "low": 200, "clip": 4096}[codes]
    lo = {"any": 0, "high": 4000, "low": 0, "clip": 4094}[codes]
    raw = rng.integers(lo, hi, shape).astype(np.uint16)
    try:
        v, s = validity.classify(raw, prof, mode=mode, l_min=l_min)
    except validity.FrameError:
        assert mode == "bogus" or l_min is not None
        return
    assert np.isfinite(v).all()
    crosstalk.correct(v, s, prof, mode="lut")
    known = validity.known_mask(s)
    lower, upper = validity.bounds(v, s)
    out = reconstruction.reconstruct(v, known, method=method, lower=lower, upper=upper)
    assert out.shape == shape and np.isfinite(out).all()
    img = tonemap.log_tonemap(out, prof.white)
    assert img.shape == shape


@FUZZ
@given(shape=st.tuples(st.integers(1, 20), st.integers(1, 20)), seed=st.integers(0, 2 ** 16),
       bad=st.sampled_from([np.nan, np.inf, -np.inf, 1e38, -1e38]), where=st.sampled_from(["known", "missing"]),
       method=st.sampled_from(["preview", "nearest", "linear", "fse"]))
def test_fuzz_hdr_values_nan_inf(shape, seed, bad, where, method):
    """NaN/Inf in an HDR frame: at missing pixels they are ignored, at known pixels reconstruct says so."""
    rng = np.random.default_rng(seed)
    v = rng.random(shape).astype(np.float32) * 1000
    known = rng.random(shape) < 0.5
    sel = known if where == "known" else ~known
    if not sel.any():
        return
    v[sel] = bad
    try:
        out = reconstruction.reconstruct(v, known, method=method, preset="preview" if method == "fse" else None)
    except ValueError as e:
        assert where == "known" and "NaN or Inf" in str(e)
        return
    if where == "missing" and known.any():       # filled from finite known values only
        assert np.isfinite(out[~known]).all()
    tonemap.log_tonemap(out, 1000.0)       # NaN maps to black, never raises


@pytest.mark.gst
@FUZZ
@given(w=st.integers(1, 40), h=st.integers(1, 12), extra=st.integers(-64, 64), pad_rows=st.booleans())
def test_fuzz_gst_raw_buffer_strides(gst, w, h, extra, pad_rows):
    """nrvalidity's view of a raw buffer (map_video): any buffer size either maps to an (H, W) view of whole
    rows or raises ValueError saying what was expected; never reads past the buffer."""
    from gi.repository import GstVideo
    from gst_plugins.elements._common import map_video
    caps = gst.Caps.from_string(f"video/x-raw,format=GRAY16_LE,width={w},height={h},framerate=5/1")
    vi = GstVideo.VideoInfo.new_from_caps(caps)
    size = max(0, (vi.size if pad_rows else 2 * w * h) + extra)
    # (Gst.Buffer.new_wrapped(b"") crashes PyGObject 3.42 itself: allocate instead)
    buf = gst.Buffer.new_allocate(None, size, None) if size else gst.Buffer.new()
    try:
        with map_video(buf, vi, "<u2", write=False) as a:
            assert a.shape == (h, w)
            stride = a.strides[0]
            assert stride >= 2 * w and (h - 1) * stride + 2 * w <= size
            int(a.sum())
    except ValueError as e:
        assert "does not hold" in str(e)
