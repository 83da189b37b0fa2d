"""Files received from others (docs/RELIABILITY.md): paths named by a profile, calibration, clip.json or
exposures.csv stay in the folder of the file naming them; JSON is size- and depth-capped; image headers are
checked before decoding; truncated images are errors; calibration values are checked; scenes that cannot be
exposed and non-finite or out-of-range command-line numbers are refused."""
from __future__ import annotations

import json
import os
import re
import shlex
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest

from gst_plugins import cli
from nrhdr_core import calibration, crosstalk, io, profile, simulate


def _profile(d: Path, calibrated: bool = False, name: str = "cam") -> Path:
    d.mkdir(parents=True, exist_ok=True)
    p = profile.default(12, 16, seed=2)
    if calibrated:
        p = p.replace(crosstalk=crosstalk.identity_calibration(p.mask))
    return profile.save(p, d / f"{name}.json")


def _edit(path: Path, **changes) -> None:
    doc = json.loads(path.read_text())
    for k, v in changes.items():
        if "." in k:
            a, b = k.split(".")
            doc[a][b] = v
        else:
            doc[k] = v
    path.write_text(json.dumps(doc))


def png_bytes(width: int, height: int, rows: bytes = b"", bit_depth: int = 8, colour: int = 0,
              pad: int = 0) -> bytes:
    """A PNG whose header declares width x height; its image data is `rows` compressed (may be short);
    `pad` bytes of an ancillary chunk make the file look big enough for its header (as a real
    decompression bomb: zeros compress about 1000:1)."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + (chunk(b"zpAd", bytes(pad)) if pad else b"")
            + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


# ---- paths named by files -------------------------------------------------------------------------------

@pytest.mark.parametrize("how", ["dotdot", "absolute", "symlink"])
def test_profile_mask_outside_its_folder_is_refused(tmp_path, how):
    f = _profile(tmp_path / "recv")
    outside = tmp_path / "elsewhere_mask.png"
    os.replace(f.parent / "cam_mask.png", outside)
    name = {"dotdot": "../elsewhere_mask.png", "absolute": str(outside), "symlink": "link.png"}[how]
    if how == "symlink":
        os.symlink(outside, f.parent / "link.png")
    _edit(f, mask=name)
    with pytest.raises(profile.ProfileError) as e:
        profile.load(f)
    msg = str(e.value)
    assert str(f) in msg and "'mask'" in msg and name in msg and "allow_outside" in msg
    assert profile.load(f, allow_outside=True).mask.shape == (12, 16)     # the user's explicit choice


def test_profile_files_in_subfolders_and_dotdot_inside_are_accepted(tmp_path):
    f = _profile(tmp_path / "recv")
    (f.parent / "masks").mkdir()
    os.replace(f.parent / "cam_mask.png", f.parent / "masks" / "m.png")
    _edit(f, mask="masks/../masks/m.png")
    assert profile.load(f).mask.shape == (12, 16)


def test_calibration_file_outside_the_profile_folder_is_refused(tmp_path):
    f = _profile(tmp_path / "recv", calibrated=True)
    os.replace(f.parent / "cam_crosstalk.npz", tmp_path / "x.npz")
    _edit(f, **{"crosstalk.file": "../x.npz"})
    with pytest.raises(profile.ProfileError, match=r"cam\.json: field 'crosstalk'.*'crosstalk.file'.*\.\./x\.npz"):
        profile.load(f)
    assert profile.load(f, allow_outside=True).crosstalk is not None


def test_clip_json_naming_a_file_outside_the_clip_is_refused(tmp_path):
    from conftest import make_test_clip
    d, _, _ = make_test_clip(tmp_path / "clip", frames=2)
    secret = tmp_path / "secret.raw"
    secret.write_bytes(b"\0" * (2 * 64 * 48))
    _edit(d / "clip.json", raw="../secret.raw")
    with pytest.raises(simulate.ClipError, match=r"clip\.json: field 'raw': '\.\./secret\.raw' leaves the folder"):
        simulate.load_clip(d)
    assert simulate.load_clip(d, allow_outside=True)["raw_path"] == str(d.resolve() / "../secret.raw")
    _edit(d / "clip.json", raw="clip.raw", profile=str(tmp_path / "other.json"))
    with pytest.raises(simulate.ClipError, match="field 'profile'.*absolute path"):
        simulate.load_clip(d)


def test_clip_json_paths_and_numbers_resolved_and_checked(tmp_path):
    from conftest import make_test_clip
    d, _, _ = make_test_clip(tmp_path / "clip", frames=2)
    info = simulate.load_clip(d)
    assert info["raw_path"] == str(d.resolve() / "clip.raw")
    assert info["profile_path"] == str(d.resolve() / "camera.json")
    for field, bad in (("width", 0), ("height", "48"), ("fps", 1e9), ("frames", True), ("version", 2)):
        doc = json.loads((d / "clip.json").read_text())
        (d / "clip.json").write_text(json.dumps(dict(doc, **{field: bad})))
        with pytest.raises(simulate.ClipError, match=f"field '{field}'"):
            simulate.load_clip(d)
        (d / "clip.json").write_text(json.dumps(doc))


def test_flats_index_naming_a_frame_outside_the_folder_is_refused(tmp_path):
    d = tmp_path / "flats"
    d.mkdir()
    io.write_image(tmp_path / "outside.tif", np.zeros((4, 5), np.uint16), np.uint16)
    (d / "exposures.csv").write_text("file,exposure_s\n../outside.tif,0\n")
    with pytest.raises(calibration.CalibrationError,
                       match=r"exposures\.csv: field 'file \(line 2\)': '\.\./outside\.tif' leaves the folder"):
        calibration.read_index(d)


# ---- JSON size and depth --------------------------------------------------------------------------------

@pytest.mark.parametrize("text", ["[" * 100000 + "]" * 100000, '{"a":' * 5000 + "1" + "}" * 5000])
def test_deeply_nested_json_is_a_profile_error(tmp_path, text):
    f = tmp_path / "cam.json"
    f.write_text(text)
    with pytest.raises(profile.ProfileError, match=r"cam\.json: not a valid JSON camera profile: nested \d+ levels"):
        profile.load(f)


def test_read_json_refuses_big_non_utf8_and_non_objects(tmp_path):
    f = tmp_path / "x.json"
    f.write_bytes(b'{"a": "' + b"x" * (io.JSON_MAX_BYTES + 10) + b'"}')
    with pytest.raises(io.FileContentError, match=f"larger than {io.JSON_MAX_BYTES} bytes"):
        io.read_json(f)
    f.write_bytes(b'{"a": "\xff"}')
    with pytest.raises(io.FileContentError, match="not UTF-8"):
        io.read_json(f)
    f.write_text("[1, 2]")
    with pytest.raises(io.FileContentError, match="top level must be an object"):
        io.read_json(f)
    f.write_text('{"s": "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["}')    # brackets inside a string
    assert io.read_json(f)["s"].startswith("[[")


# ---- images: headers before pixels, truncation -------------------------------------------------------------

def test_mask_declaring_60000x60000_pixels_is_refused_from_its_header(tmp_path):
    f = _profile(tmp_path / "recv")
    (f.parent / "cam_mask.png").write_bytes(png_bytes(60000, 60000, b"\0" * 100, pad=4 << 20))
    with pytest.raises(profile.ProfileError, match=r"cam\.json: field 'mask'.*60000x60000.*nothing was decoded"):
        profile.load(f)
    _edit(f, width=60000, height=60000)       # even where the profile claims that size: the pixel cap
    with pytest.raises(profile.ProfileError, match=r"declares 60000x60000 pixels.*nothing was decoded"):
        profile.load(f)
    (f.parent / "cam_mask.png").write_bytes(png_bytes(60000, 60000, b"\0" * 100))    # OpenImageIO's own check
    with pytest.raises(profile.ProfileError, match=r"cam\.json: field 'mask'.*cam_mask\.png"):
        profile.load(f)


@pytest.mark.parametrize("ext", ["exr", "png", "tif"])
def test_truncated_images_are_errors_naming_the_file(tmp_path, ext):
    f = tmp_path / f"frame_00000.{ext}"
    a = (np.random.default_rng(1).random((40, 50)) * 60000).astype(np.uint16)
    if ext == "exr":
        io.write_exr(f, a.astype(np.float32))
    else:
        io.write_image(f, a, np.uint16)
    b = f.read_bytes()
    f.write_bytes(b[: len(b) // 2])
    with pytest.raises(io.ImageFileError, match=re.escape(str(f))):
        io.read_image(f, np.float32)
    if ext == "exr":
        with pytest.raises(io.ImageFileError, match="truncated or corrupt"):
            io.read_exr(f)


def test_compare_refuses_a_truncated_exr(tmp_path, capsys):
    prof = profile.default(24, 32)
    pf = profile.save(prof, tmp_path / "cam.json")
    (tmp_path / "truth").mkdir()
    (tmp_path / "out").mkdir()
    t = np.full((24, 32), 1000.0, np.float32)
    io.write_exr(tmp_path / "truth" / "frame_00000.exr", t)
    noisy = t * (1 + 0.1 * np.random.default_rng(0).random(t.shape)).astype(np.float32)
    io.write_exr(tmp_path / "out" / "frame_00000.exr", noisy, np.zeros((24, 32), np.uint8))
    b = (tmp_path / "out" / "frame_00000.exr").read_bytes()
    (tmp_path / "out" / "frame_00000.exr").write_bytes(b[: len(b) - 200])     # the pixels cut short
    rc = cli.main(["compare", str(tmp_path / "out"), "--truth", str(tmp_path / "truth"), "--profile", str(pf)])
    err = capsys.readouterr().err
    assert rc == 2 and str(tmp_path / "out" / "frame_00000.exr") in err and "truncated or corrupt" in err


# ---- calibration values -----------------------------------------------------------------------------------

@pytest.mark.parametrize("field,value,expect", [
    ("qscale", float("nan"), "qscale"), ("qoffset", float("inf"), "qoffset"), ("qscale", 0.0, "qscale"),
    ("black_level", -1.0, "black_level"), ("clip_code", 4094.5, "clip_code"), ("nd", 1e308, "nd"),
    ("version", 2, "version 1"), ("clip_code", 70000, "clip_code")])
def test_calibration_entry_numbers_are_checked(tmp_path, field, value, expect):
    f = _profile(tmp_path / "recv", calibrated=True)
    _edit(f, **{f"crosstalk.{field}": value})
    with pytest.raises(profile.ProfileError, match=rf"cam\.json: field 'crosstalk'.*{expect}"):
        profile.load(f)


@pytest.mark.parametrize("damage", ["reversed_codes", "reversed_knot_flux", "equal_knot_flux", "nan_alpha",
                                    "inf_clip_flux", "other_shape", "float_knot_counts"])
def test_calibration_arrays_are_checked(tmp_path, damage):
    f = _profile(tmp_path / "recv", calibrated=True)
    npz = f.parent / "cam_crosstalk.npz"
    with np.load(npz) as z:
        a = {k: z[k].copy() for k in z.files}
    if damage == "reversed_codes":
        a["codes_q"] = a["codes_q"][:, :, ::-1].copy()
    elif damage == "reversed_knot_flux":
        a["knot_flux"] = a["knot_flux"][::-1].copy()
    elif damage == "equal_knot_flux":
        a["knot_flux"][2] = a["knot_flux"][1]
    elif damage == "nan_alpha":
        a["alpha"][3, 4] = np.nan
    elif damage == "inf_clip_flux":
        a["clip_flux"][0, 0] = np.inf
    elif damage == "other_shape":
        a["clip_flux"] = a["clip_flux"][:, :-1]
    else:
        a["n_knots"] = a["n_knots"].astype(np.float32) + 0.5
    np.savez(npz, **a)
    with pytest.raises(profile.ProfileError, match=r"cam\.json: field 'crosstalk': .*cam_crosstalk\.npz"):
        profile.load(f)


def test_calibration_array_declaring_a_huge_shape_is_refused_from_its_header(tmp_path):
    """An .npz member whose .npy header declares 60000 x 60000 x 255 codes (900 GB) with 64 bytes of data:
    refused from the header, nothing is decompressed."""
    import io as pyio
    import zipfile
    f = _profile(tmp_path / "recv", calibrated=True)
    npz = f.parent / "cam_crosstalk.npz"
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    with zipfile.ZipFile(npz, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in arrays.items():
            b = pyio.BytesIO()
            if k == "codes_q":
                np.lib.format.write_array_header_1_0(b, {"descr": "<u2", "fortran_order": False,
                                                         "shape": (60000, 60000, 255)})
                b.write(bytes(64))
            else:
                np.lib.format.write_array(b, v)
            zf.writestr(k + ".npy", b.getvalue())
    with pytest.raises(profile.ProfileError, match=r"array codes_q is uint16 \(60000, 60000, 255\), expected uint16 "
                                                   r"\(12, 16, K\)"):
        profile.load(f)


def test_calibration_of_another_sensor_is_refused_by_check_same_sensor(tmp_path):
    a = profile.load(_profile(tmp_path / "a", calibrated=True))
    other = profile.make(~a.mask)
    with pytest.raises(profile.ProfileError, match="another sensor"):
        profile.check_same_sensor(a, other)
    profile.check_same_sensor(a, profile.make(a.mask.copy()))


# ---- scenes --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("value", [3e38, 1e-40])
def test_scene_that_cannot_be_exposed_is_refused_before_writing(tmp_path, value):
    scene = np.full((20, 20), value, np.float32)
    with pytest.raises(ValueError, match="cannot be exposed"):
        simulate.simulate_clip(scene, tmp_path / "c", profile.default(8, 8), frames=1, progress=False)
    assert not (tmp_path / "c").exists()


def test_scene_file_with_nan_is_refused_by_simulate(tmp_path, capsys):
    s = np.ones((16, 16), np.float32)
    s[3, 3] = np.nan
    io.write_image(tmp_path / "s.exr", s, np.float32)
    rc = cli.main(["simulate", str(tmp_path / "s.exr"), "-o", str(tmp_path / "c"), "--frames", "1",
                   "--width", "8", "--height", "8"])
    assert rc == 2 and "1 of 256 pixels are NaN or infinite" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


# ---- command-line numbers ------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv,option", [
    (["simulate", "-o", "x", "--exposure", "nan"], "--exposure"),
    (["simulate", "-o", "x", "--exposure", "1e308"], "--exposure"),
    (["simulate", "-o", "x", "--frames", "1e9"], "--frames"),
    (["simulate", "-o", "x", "--nd", "inf"], "--nd"),
    (["simulate", "-o", "x", "--width", "0"], "--width"),
    (["simulate", "-o", "x", "--zoom", "0"], "--zoom"),
    (["profile", "-o", "x", "--l-min", "-1"], "--l-min"),
    (["demo", "--frames", "-3"], "--frames"),
    (["calibrate", "f", "--mask", "m", "-o", "x", "--bit-depth", "17"], "--bit-depth"),
    (["calibrate", "f", "--mask", "m", "-o", "x", "--nd-nominal", "nan"], "--nd-nominal"),
    (["simulate-flats", "x", "--exposures", "3"], "--exposures"),
    (["simulate-flats", "x", "--seed", "-1"], "--seed"),
    (["compare", "d", "--truth", "t", "--profile", "p", "--frames", "-1"], "--frames"),
    (["snr", "--nd", "0.5"], "--nd"),
    (["figures", "-o", "x", "--seed", "1.5"], "--seed")])
def test_cli_numbers_out_of_range_are_refused(argv, option, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert f"argument {option}:" in err and "Traceback" not in err
    assert not list(tmp_path.iterdir())


# ---- printed commands paste into bash -------------------------------------------------------------------

def test_simulate_prints_a_launch_line_that_bash_runs_as_printed(tmp_path, capsys):
    out = tmp_path / "my clips" / "c 1"
    rc = cli.main(["simulate", "-o", str(out), "--frames", "1", "--width", "30", "--height", "20"])
    assert rc == 0
    line = next(ln.strip() for ln in capsys.readouterr().out.splitlines() if ln.strip().startswith("nrhdr launch"))
    p = subprocess.run(["bash", "-c", 'nrhdr() { printf "%s\\n" "$@"; }\n' + line], capture_output=True,
                       text=True, timeout=30)
    assert p.returncode == 0, p.stderr
    args = p.stdout.splitlines()
    assert args[:3] == ["launch", "filesrc", f"location={out / 'clip.raw'}"]
    assert "plane-strides=<60>" in args and f"profile={out / 'camera.json'}" in args
    assert args == shlex.split(line)[1:]


@pytest.mark.gst
def test_simulate_launch_line_runs_the_clip(tmp_path, capsys, gst_subprocess_env):
    import sys
    out = tmp_path / "a clip"
    assert cli.main(["simulate", "-o", str(out), "--frames", "2", "--width", "32", "--height", "24"]) == 0
    line = next(ln.strip() for ln in capsys.readouterr().out.splitlines() if ln.strip().startswith("nrhdr launch"))
    line = line.replace("nrreconstruct", "nrreconstruct method=nearest").replace("autovideosink", "fakesink")
    script = f'nrhdr() {{ {shlex.quote(sys.executable)} -m gst_plugins.cli "$@"; }}\n{line}'
    root = Path(__file__).resolve().parents[1]
    p = subprocess.run(["bash", "-c", script], cwd=root, env=gst_subprocess_env, capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]


@pytest.mark.gst
def test_demo_prints_only_paths_that_exist_after_it_ends(tmp_path, capsys):
    out = tmp_path / "demo"
    rc = cli.main(["demo", "-o", str(out), "--frames", "2", "--width", "32", "--height", "24",
                   "--method", "nearest"])
    assert rc == 0
    text = capsys.readouterr()
    paths = re.findall(re.escape(str(tmp_path)) + r"[^\s:!]*", text.out + text.err)
    assert paths and any("png" in p for p in paths)
    for p in paths:
        p = p.rstrip("/,)'")
        if "%05d" in p:
            p = p % 0
        assert os.path.exists(p), f"printed {p}, which does not exist"
    line = next(x for x in text.out.splitlines() if x.startswith("pipeline: "))[len("pipeline: "):]
    words = shlex.split(line)                                   # as bash splits the pasted line
    assert words[:2] == ["nrhdr", "launch"] and "plane-strides=<64>" in words and "!" in words


@pytest.mark.gst
@pytest.mark.parametrize("allow", [False, True])
def test_elements_refuse_a_profile_naming_files_outside_unless_allowed(tmp_path, gst_subprocess_env, allow):
    """nrvalidity reads a profile whose mask lies outside its folder only with allow-outside-paths=true;
    nrcrosstalk and nrreconstruct then read the same profile from the caps as nrvalidity did."""
    import sys
    f = _profile(tmp_path / "recv", calibrated=True)
    os.replace(f.parent / "cam_mask.png", tmp_path / "shared_mask.png")
    _edit(f, mask="../shared_mask.png")
    flag = " allow-outside-paths=true" if allow else ""
    pipeline = (f"videotestsrc num-buffers=3 ! video/x-raw,format=GRAY16_LE,width=16,height=12 "
                f"! nrvalidity profile={shlex.quote(str(f))}{flag} ! nrcrosstalk mode=lut "
                f"! nrreconstruct method=nearest ! fakesink")
    root = Path(__file__).resolve().parents[1]
    p = subprocess.run([sys.executable, "-m", "gst_plugins.cli", "launch", *shlex.split(pipeline)], cwd=root,
                       env=gst_subprocess_env, capture_output=True, text=True, timeout=300)
    out = p.stdout + p.stderr
    if allow:
        assert p.returncode == 0, out[-3000:]
    else:
        assert p.returncode != 0
        assert "nrvalidity" in out and "'mask'" in out and "../shared_mask.png" in out, out[-3000:]
