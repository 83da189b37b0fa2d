"""Image and video files: OpenImageIO for images (PNG, TIFF, OpenEXR, Radiance .hdr), numpy for raw video.

Every writer is atomic: it writes to a temporary file beside the target and renames it, so a file is
written completely or not at all.
"""
from __future__ import annotations

import dataclasses
import json
import os
import re
import tempfile
from pathlib import Path

import numpy as np

# Rec. 709 / sRGB luminance weights for linear RGB.
LUMA_709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)


class FileContentError(ValueError):
    """An input file is unreadable, too large, or holds unexpected content; the message names the file (and
    the field). The loaders re-raise it as their own error type (ProfileError, CalibrationError, ClipError)."""


class ImageFileError(FileContentError):
    """An image could not be read or has unexpected content; the message names the file."""


class ImageSizeError(ImageFileError):
    """An image's header declares another size than the one it must have (nothing was decoded)."""


class OutputExistsError(FileExistsError):
    """A command would replace a file or folder it was not told to replace (`--force`, `overwrite`)."""


def _oiio():
    import OpenImageIO as oiio  # imported lazily: keeps `import nrhdr_core` light
    return oiio


# ======================================================================================================
# Files received from others: JSON and the paths it names (docs/RELIABILITY.md)
# ======================================================================================================

JSON_MAX_BYTES = 4 << 20    # a profile or clip.json is a few kB; a calibration's info a few tens of kB
JSON_MAX_DEPTH = 32         # the deepest document nrhdr writes nests 4 levels
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.S)
_JSON_BRACKET = re.compile(r"[\[\]{}]")


def read_json(path, what: str = "JSON file", error=FileContentError, max_bytes: int = JSON_MAX_BYTES,
              max_depth: int = JSON_MAX_DEPTH) -> dict:
    """The one JSON reader for files nrhdr receives (profiles, clip.json, manifests): at most `max_bytes`
    bytes, UTF-8, nested at most `max_depth` levels, a JSON object at the top. Any failure raises `error`
    with a message naming the file and `what` it should be."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except OSError as e:
        raise error(f"{path}: cannot read the {what}: {e.strerror or e}") from None
    if len(data) > max_bytes:
        raise error(f"{path}: larger than {max_bytes} bytes: not a {what}")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"{path}: not a valid {what}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    depth = deepest = 0
    for b in _JSON_BRACKET.findall(_JSON_STRING.sub("", text)):
        depth += 1 if b in "[{" else -1
        deepest = max(deepest, depth)
    if deepest > max_depth:
        raise error(f"{path}: not a valid {what}: nested {deepest} levels deep (at most {max_depth})")
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError) as e:      # JSONDecodeError, integers of more than 4300 digits
        raise error(f"{path}: not a valid {what}: {e}") from None
    if not isinstance(doc, dict):
        raise error(f"{path}: not a valid {what}: the top level must be an object, got {type(doc).__name__}")
    return doc


_TRUST_HINT = ("if you trust this file: allow_outside=True, the option --allow-outside-paths or the element "
               "property allow-outside-paths=true")


def resolve_named(source, field: str, name, error=FileContentError, allow_outside: bool = False) -> Path:
    """The path that `field` of file `source` (a JSON or CSV file received from someone) names, relative to
    the folder holding `source`. Unless `allow_outside`, a name that leaves that folder is refused: an
    absolute path, `..` above it, or a symbolic link pointing out of it; the error names `source`, `field`
    and the name. The folder itself may be reached through a link (the user named it)."""
    source = Path(source)
    if not isinstance(name, str) or not name or "\x00" in name:
        raise error(f"{source}: field '{field}' must name a file, got {name!r}")
    base = Path(os.path.abspath(source.parent))
    target = base / name                      # an absolute `name` replaces base
    if allow_outside:
        return target
    if os.path.isabs(name):
        raise error(f"{source}: field '{field}': {name!r} is an absolute path; a file named here must lie in "
                    f"{base} ({_TRUST_HINT})")
    try:
        real_base, real = base.resolve(), target.resolve()
    except (OSError, RuntimeError) as e:        # a symlink loop
        raise error(f"{source}: field '{field}': cannot resolve {name!r}: {e}") from None
    if real != real_base and real_base not in real.parents:
        how = "leaves" if ".." in Path(name).parts else "is a link out of"
        raise error(f"{source}: field '{field}': {name!r} {how} the folder {base} (it resolves to {real}); a "
                    f"file named here must lie in that folder ({_TRUST_HINT})")
    return target


# ======================================================================================================
# Images: the header is checked before any pixel is decoded, every decoder error surfaces
# ======================================================================================================

MAX_PIXELS = 1 << 27        # 16384 x 8192: larger images are refused before decoding (a decompression bomb)
MAX_CHANNELS = 64


def _read_pixels(path, fmt_of, shape=None, channels=None, check=None, one_image=False, decode=True):
    """Open `path` with OpenImageIO, check its header (2-D, at most MAX_PIXELS pixels and MAX_CHANNELS
    channels, `shape` (H, W) where given, `check(spec)`, with `one_image` a single image: no second page
    or subimage), then decode channels `channels(spec)` -> (begin, end) (default all) as `fmt_of(spec)`;
    returns (pixels (H, W, C), spec, channel names); pixels None without `decode` (the header only).
    Errors: ImageFileError naming the file, also for a truncated or corrupt file."""
    oiio = _oiio()
    path = str(path)
    if not os.path.isfile(path):
        raise ImageFileError(f"{path}: no such file")
    try:
        return _decode(oiio, path, fmt_of, shape, channels, check, one_image, decode)
    except UnicodeDecodeError:      # a corrupt header's names reach us through OpenImageIO's messages
        raise ImageFileError(f"{path}: cannot read image: its header holds text that is not UTF-8 (corrupt "
                             f"file?)") from None


def _error_text(get) -> str:
    try:
        return (get() or "").strip()
    except UnicodeDecodeError:
        return "(an error message that is not UTF-8)"


def _decode(oiio, path, fmt_of, shape, channels, check, one_image=False, decode=True):
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ImageFileError(f"{path}: cannot read image: {_error_text(oiio.geterror)}")
    try:
        spec = inp.spec()
        names = [str(n) for n in spec.channelnames]
        w, h, d, c = int(spec.width), int(spec.height), int(spec.depth), int(spec.nchannels)
        if w < 1 or h < 1 or d != 1 or c < 1:
            raise ImageFileError(f"{path}: not a 2-D image ({w}x{h}x{d}, {c} channels)")
        if w * h > MAX_PIXELS or c > MAX_CHANNELS:
            raise ImageFileError(f"{path}: the header declares {w}x{h} pixels, {c} channels: more than nrhdr "
                                 f"reads ({MAX_PIXELS} pixels, {MAX_CHANNELS} channels); nothing was decoded")
        if shape is not None and (h, w) != tuple(shape):
            raise ImageSizeError(f"{path}: image is {w}x{h}, expected {shape[1]}x{shape[0]}; nothing was "
                                 f"decoded")
        if check is not None:
            check(spec)
        if one_image:
            if inp.seek_subimage(1, 0):
                raise ImageFileError(f"{path}: holds more than one image (pages or subimages); one frame per "
                                     f"file is read")
            _error_text(inp.geterror)       # clears the failed seek's message: not an error of the file
            inp.seek_subimage(0, 0)
        if not decode:
            return None, spec, names
        cb, ce = channels(spec) if channels is not None else (0, c)
        px = inp.read_image(0, 0, cb, ce, fmt_of(spec))
        err = _error_text(inp.geterror) if inp.has_error else ""
        if px is None or err:
            raise ImageFileError(f"{path}: cannot decode pixels (truncated or corrupt file?): "
                                 f"{err or _error_text(oiio.geterror) or 'read failed'}")
    finally:
        inp.close()
    px = np.asarray(px)
    if px.ndim == 2:
        px = px[:, :, None]
    if px.shape[:2] != (h, w):
        raise ImageFileError(f"{path}: decoded {px.shape[1]}x{px.shape[0]} pixels, header says {w}x{h}")
    return px, spec, names


def read_image(path, dtype=np.float32, shape=None) -> np.ndarray:
    """Read any image OpenImageIO supports as (H, W, C) array of `dtype` (float: values as stored for
    float files, 0..1 for integer files; uint8/uint16: native codes). `shape` (H, W): the size it must have,
    checked before decoding."""
    oiio = _oiio()
    fmt = {np.dtype(np.float32): oiio.FLOAT, np.dtype(np.uint8): oiio.UINT8,
           np.dtype(np.uint16): oiio.UINT16, np.dtype(np.float64): oiio.DOUBLE}[np.dtype(dtype)]
    return _read_pixels(path, lambda spec: fmt, shape)[0]


def _nonfinite_policy(nonfinite: str) -> None:
    if nonfinite not in ("repair", "error"):
        raise ValueError(f"nonfinite must be 'repair' or 'error', got {nonfinite!r}")


def _clean(a: np.ndarray, path, nonfinite: str, unit: str) -> np.ndarray:
    """`a` (float64) with NaN/Inf handled by `nonfinite` ("repair": NaN, -Inf -> 0, +Inf -> the largest
    finite value; "error": ImageFileError counting them) and negative values clamped to 0, as float32;
    nothing finite is always an error."""
    finite = np.isfinite(a)
    if not finite.any():
        raise ImageFileError(f"{path}: no finite pixel values")
    if not finite.all():
        if nonfinite == "error":
            raise ImageFileError(f"{path}: {int(np.sum(~finite))} of {a.size} {unit} are NaN or infinite")
        big = float(np.max(a[finite]))
        a = np.where(np.isnan(a), 0.0, a)
        a = np.where(np.isposinf(a), big, a)
        a = np.where(np.isneginf(a), 0.0, a)
    return np.maximum(a, 0.0).astype(np.float32)


def _read_float(path) -> np.ndarray:
    """The first (at most four) channels of an image as float64 (H, W, C)."""
    oiio = _oiio()
    px = _read_pixels(path, lambda spec: oiio.FLOAT, channels=lambda spec: (0, min(int(spec.nchannels), 4)))[0]
    return px.astype(np.float64)


def read_luminance(path, nonfinite: str = "repair") -> np.ndarray:
    """Read an HDR (or LDR) image as linear luminance float32 (H, W).

    RGB(A) is converted with Rec. 709 weights; negative values (present in some EXR scenes) are clamped
    to 0. NaN/Inf: `nonfinite="repair"` replaces them by 0 (NaN, -Inf) or the largest finite value (+Inf),
    "error" raises ImageFileError counting them; nothing finite left is always an error."""
    _nonfinite_policy(nonfinite)
    px = _read_float(path)
    c = px.shape[2]
    with np.errstate(over="ignore", invalid="ignore"):
        if c >= 3:
            lum = px[:, :, :3] @ LUMA_709
        else:
            lum = px[:, :, 0]
    return _clean(lum, path, nonfinite, "pixels")


def read_rgb(path, nonfinite: str = "repair") -> np.ndarray:
    """Read an HDR (or LDR) image as linear RGB, planar float32 (3, H, W), channels R, G, B (docs/COLOUR.md).

    Values as stored (float files) or 0..1 (integer files), as `read_luminance` reads them, so that the
    Rec. 709 luminance of the result is `read_luminance`'s; a file of one or two channels (gray, gray +
    alpha) gives three equal planes, alpha is ignored. Negative values are clamped to 0; NaN/Inf follow
    `nonfinite` as in `read_luminance` (the largest finite value over all three channels for +Inf)."""
    _nonfinite_policy(nonfinite)
    px = _read_float(path)
    rgb = px[:, :, :3] if px.shape[2] >= 3 else np.repeat(px[:, :, :1], 3, axis=2)
    return np.ascontiguousarray(np.moveaxis(_clean(rgb, path, nonfinite, "values"), 2, 0))


def _atomic_target(path):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + path.stem + ".", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the final file the usual mode
    return path, Path(tmp)


def write_image(path, array, dtype=None, channel_names=None, attributes=None) -> Path:
    """Write (H, W) or (H, W, C) `array` atomically with OpenImageIO. `dtype` picks the file's pixel
    type (np.uint8, np.uint16, np.float16, np.float32); default: the array's own."""
    oiio = _oiio()
    arr = np.asarray(array)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    h, w, c = arr.shape
    dtype = np.dtype(dtype or arr.dtype)
    tdesc = {np.dtype(np.uint8): oiio.UINT8, np.dtype(np.uint16): oiio.UINT16,
             np.dtype(np.float16): oiio.HALF, np.dtype(np.float32): oiio.FLOAT}[dtype]
    spec = oiio.ImageSpec(w, h, c, tdesc)
    if channel_names:
        spec.channelnames = tuple(channel_names)
    for k, v in (attributes or {}).items():
        spec.attribute(k, v)
    path, tmp = _atomic_target(path)
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        tmp.unlink(missing_ok=True)
        raise ImageFileError(f"{path}: no OpenImageIO writer for this file type: {oiio.geterror()}")
    try:
        if not out.open(str(tmp), spec):
            raise ImageFileError(f"{path}: cannot open for writing: {out.geterror()}")
        src = np.ascontiguousarray(arr.astype(dtype, copy=False))
        ok = out.write_image(src)
        ok = out.close() and ok
        if not ok:
            raise ImageFileError(f"{path}: write failed: {out.geterror()}")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


EXR_RGB = ("R", "G", "B")


def write_exr(path, values, state=None) -> Path:
    """Write a linear HDR frame as OpenEXR: float32 (H, W) `values` as channel "Y", planar (3, H, W) colour
    values as channels "R", "G", "B"; with `state` (H, W), one more channel "state" keeps the per-pixel
    validity state (docs/ARCHITECTURE.md; of the mosaic for colour, docs/COLOUR.md) so a recording loses
    nothing."""
    v = np.asarray(values, dtype=np.float32)
    if v.ndim == 3:
        if v.shape[0] != 3:
            raise ValueError(f"{path}: colour values must be planar (3, H, W), got shape {v.shape}")
        planes, names = list(v), list(EXR_RGB)
    elif v.ndim == 2:
        if state is None:
            return write_image(path, v, np.float32, ["Y"])
        planes, names = [v], ["Y"]
    else:
        raise ValueError(f"{path}: values must be (H, W) or (3, H, W), got shape {v.shape}")
    if state is not None:
        st = np.asarray(state)
        if st.shape != v.shape[-2:]:
            raise ValueError(f"{path}: state must be {v.shape[-2:]} like the values, got shape {st.shape}")
        planes, names = planes + [st.astype(np.float32)], names + ["state"]
    return write_image(path, np.stack(planes, axis=-1), np.float32, names)


# OpenImageIO colour spaces that write a PNG cICP chunk (ITU-T H.273: primaries 9 = BT.2020, transfer 16 = PQ
# or 18 = HLG, matrix 0 = RGB, full range) and no sRGB/gAMA/cHRM chunks to contradict it
HDR_PNG_COLORSPACES = {"pq": "pq_rec2020_display", "hlg": "hlg_rec2020_display"}


def write_hdr_png(path, signal, transfer: str = "pq") -> Path:
    """Write an HDR still: a 16-bit PNG of full-range BT.2100 signal words (uint16, 0..65535 = signal 0..1,
    grey (H, W) or (H, W, C)) with a cICP chunk saying BT.2020 primaries and PQ or HLG (`transfer`)."""
    if transfer not in HDR_PNG_COLORSPACES:
        raise ValueError(f"HDR PNG transfer must be one of {', '.join(HDR_PNG_COLORSPACES)}, got {transfer!r}")
    if Path(path).suffix.lower() != ".png":
        raise ValueError(f"{path}: an HDR still with cICP must be a .png file")
    return write_image(path, np.asarray(signal, np.uint16), np.uint16,
                       attributes={"oiio:ColorSpace": HDR_PNG_COLORSPACES[transfer]})


def read_exr(path, shape=None):
    """Read an EXR written by `write_exr`: returns (values, state uint8 (H, W) or None); values float32
    (H, W) from channel "Y" (else the first channel), or planar (3, H, W) from channels "R", "G", "B" when
    the file has them and no "Y". `shape` (H, W): the size it must have (checked before decoding). A
    truncated or corrupt file is an ImageFileError naming it."""
    oiio = _oiio()
    px, spec, names = _read_pixels(path, lambda spec: oiio.FLOAT, shape)
    state = None
    if "state" in names:
        sv = px[:, :, names.index("state")]
        if not (np.isfinite(sv).all() and sv.min(initial=0) >= 0 and sv.max(initial=0) <= 255):
            raise ImageFileError(f"{path}: channel 'state' must hold pixel states 0..255")
        state = sv.astype(np.uint8)
    if "Y" not in names and all(n in names for n in EXR_RGB):
        return np.stack([px[:, :, names.index(n)] for n in EXR_RGB]), state
    vi = names.index("Y") if "Y" in names else 0
    return px[:, :, vi].copy(), state


def exr_channels(path) -> int:
    """How many colour channels `read_exr` returns for the EXR `path`: 3 (channels R, G, B, no Y) or 1,
    from its header alone (with every header check of `read_exr`)."""
    names = _read_pixels(path, None, decode=False)[2]
    return 3 if "Y" not in names and all(n in names for n in EXR_RGB) else 1


def write_mask(path, mask) -> Path:
    """Write an ND mask as 8-bit PNG, 255 = attenuated."""
    return write_image(path, np.where(np.asarray(mask, bool), 255, 0).astype(np.uint8), np.uint8)


def read_mask(path, shape=None) -> np.ndarray:
    """Read an ND mask image: one gray channel (or equal colour channels), no alpha, holding exactly two
    levels: 0 = regular and the format's full scale = attenuated (255 for 8-bit, the PNG `write_mask`
    writes; 65535 for 16-bit). `shape` (H, W): the sensor's size, checked before decoding. Anything else is
    an ImageFileError saying what was found."""
    oiio = _oiio()
    path = str(path)

    def check(spec):
        names = [str(n) for n in spec.channelnames]
        if spec.alpha_channel >= 0 or any(n.upper() in ("A", "ALPHA") for n in names):
            raise ImageFileError(f"{path}: mask has an alpha channel (channels {', '.join(names)}); save it as "
                                 f"a gray PNG without transparency (0 = regular, 255 = attenuated)")
        if spec.format.basetype not in (oiio.UINT8, oiio.UINT16):
            raise ImageFileError(f"{path}: mask must be an 8-bit (or 16-bit) integer image, got {spec.format}")

    px, spec, _ = _read_pixels(path, lambda spec: spec.format.basetype, shape, check=check)
    bits = 8 if spec.format.basetype == oiio.UINT8 else 16
    m = px[:, :, 0]
    if px.shape[2] > 1 and not all(np.array_equal(m, px[:, :, c]) for c in range(1, px.shape[2])):
        raise ImageFileError(f"{path}: mask must be gray (all colour channels equal)")
    full = (1 << bits) - 1
    bad = (m != 0) & (m != full)
    if bad.any():
        vals = np.unique(m)
        shown = ", ".join(str(int(v)) for v in vals[:6]) + (", ..." if vals.size > 6 else "")
        raise ImageFileError(f"{path}: a {bits}-bit mask must hold only 0 (regular) and {full} (attenuated); "
                             f"it holds {vals.size} distinct values ({shown}), {int(bad.sum())} pixels "
                             f"have other values" + (" (an 8-bit mask saved as 16 bit? write 0/255 as 8-bit "
                                                      "PNG)" if bits == 16 and int(vals.max()) <= 255 else ""))
    return m == full


# ======================================================================================================
# Still sequences: raw frames stored one per file as 16-bit gray TIFF or PNG (nrimagesrc, nrhdr batch)
# ======================================================================================================

STILL_EXTENSIONS = (".tif", ".tiff", ".png")
_PRINTF = re.compile(r"%(?:%|0?\d*d)")
_NUMBERED = re.compile(r"(.*?)(\d+)(\.[^.]+)")


def _still_check(path):
    """The header check (`_read_pixels` check=) of a raw frame stored as a still."""
    oiio = _oiio()

    def check(spec):
        c, names = int(spec.nchannels), [str(n) for n in spec.channelnames]
        if c != 1:
            raise ImageFileError(f"{path}: {c} channels ({', '.join(names)}); a raw frame is one gray channel "
                                 f"of sensor codes: save it without colour or alpha")
        base = spec.format.basetype
        if base == oiio.UINT8:
            raise ImageFileError(f"{path}: an 8-bit image; a raw frame holds the sensor's codes in unsigned "
                                 f"16-bit words (an 8-bit export has lost them): save 16-bit TIFF or PNG")
        if base != oiio.UINT16:
            raise ImageFileError(f"{path}: pixel type {spec.format}; a raw frame is unsigned 16-bit integers")
        bits = spec.get_int_attribute("oiio:BitsPerSample", 16)
        if bits != 16:
            raise ImageFileError(f"{path}: {bits} bits per sample; OpenImageIO would rescale them to 16 bits "
                                 f"and lose the sensor's codes: save them as 16-bit words")
    return check


def read_still(path, shape=None) -> np.ndarray:
    """A raw frame stored as a still image: one channel of unsigned 16-bit codes (TIFF, PNG), one image per
    file; returns (H, W) uint16 as stored. `shape` (H, W): the size it must have, checked before decoding.
    Anything else (8-bit, colour, alpha, float, 10/12-bit packed TIFF samples) is an ImageFileError."""
    oiio = _oiio()
    px = _read_pixels(path, lambda spec: oiio.UINT16, shape, check=_still_check(path), one_image=True)[0]
    return np.ascontiguousarray(px[:, :, 0])


def still_size(path, shape=None) -> tuple[int, int]:
    """(H, W) of a raw still from its header, with every check of `read_still` but the decoding."""
    spec = _read_pixels(path, None, shape, check=_still_check(path), one_image=True, decode=False)[1]
    return int(spec.height), int(spec.width)


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


@dataclasses.dataclass(frozen=True)
class StillSequence:
    """A raw still sequence: `files` in frame order, each `width` x `height`, one gray 16-bit channel."""
    location: str
    files: tuple[str, ...]
    width: int
    height: int

    def __len__(self) -> int:
        return len(self.files)

    def read(self, index: int) -> np.ndarray:
        """Frame `index` as (H, W) uint16, checked again as it is read (`read_still`)."""
        return read_still(self.files[index], (self.height, self.width))


def _pattern_names(folder: Path, pattern: str, start_index: int) -> list[str]:
    """The names of a printf pattern's files, `start_index` (< 0: the lowest index present) onwards, up to
    the last one present; a gap is an error naming the missing file."""
    convs = [m.group(0) for m in _PRINTF.finditer(pattern) if m.group(0) != "%%"]
    rest = _PRINTF.sub("", pattern)
    if len(convs) != 1 or "%" in rest:
        raise ImageFileError(f"{pattern}: a file pattern holds one %d conversion (e.g. frame_%05d.tif), '%%' "
                             f"for a literal %")
    try:
        names = os.listdir(folder)
    except OSError as e:
        raise ImageFileError(f"{folder}: cannot list the folder: {e.strerror or e}") from None
    rx = re.compile(re.escape(pattern.replace("%%", "\x00")).replace(re.escape(convs[0]), r"(\d+)")
                    .replace("\x00", "%") + r"\Z")
    present = set()
    for n in names:
        m = rx.match(n)
        if m is not None and pattern % int(m.group(1)) == n:
            present.add(int(m.group(1)))
    if not present:
        raise ImageFileError(f"{folder / pattern}: no file matches the pattern")
    start = min(present) if start_index < 0 else start_index
    if start not in present:
        raise ImageFileError(f"{folder / (pattern % start)}: no such file (start-index {start}; the pattern's "
                             f"files start at index {min(present)})")
    end = start
    while end + 1 in present:
        end += 1
    later = sorted(i for i in present if i > end)
    if later:
        raise ImageFileError(f"{folder / (pattern % (end + 1))}: missing: the sequence has frames {start}..{end} "
                             f"and {len(later)} more from index {later[0]} on; frames are consecutive files "
                             f"(their timestamps are their positions)")
    return [pattern % i for i in range(start, end + 1)]


def _profile_names(folder: Path) -> set[str]:
    """The files the folder's camera profile (camera.json) names: its mask image is not a frame."""
    try:
        doc = read_json(folder / "camera.json", "camera profile")
    except FileContentError:
        return set()
    xt = doc.get("crosstalk")
    names = [doc.get("mask"), xt.get("file") if isinstance(xt, dict) else None]
    return {os.path.normpath(n) for n in names if isinstance(n, str)}


def _folder_names(folder: Path) -> list[str]:
    """The still images of a folder (STILL_EXTENSIONS, one of them; hidden files, other files and the files
    of the folder's camera.json ignored) in natural order; numbered names (one prefix, a number) must be
    consecutive."""
    try:
        entries = list(os.scandir(folder))
    except OSError as e:
        raise ImageFileError(f"{folder}: cannot list the folder: {e.strerror or e}") from None
    profile_files = _profile_names(folder) if (folder / "camera.json").is_file() else set()
    names = [e.name for e in entries if not e.name.startswith(".") and e.name not in profile_files
             and os.path.splitext(e.name)[1].lower() in STILL_EXTENSIONS and not e.is_dir()]
    if not names:
        raise ImageFileError(f"{folder}: no still images in the folder (files ending in "
                             f"{', '.join(STILL_EXTENSIONS)})")
    exts = sorted({os.path.splitext(n)[1].lower() for n in names})
    if len(exts) > 1:
        counts = ", ".join(f"{sum(os.path.splitext(n)[1].lower() == x for n in names)} {x}" for x in exts)
        raise ImageFileError(f"{folder}: holds {counts} files; a sequence folder holds one kind of file (move "
                             f"the others out, or name one kind with a pattern such as frame_%05d{exts[0]})")
    names.sort(key=_natural_key)
    parts = [_NUMBERED.fullmatch(n) for n in names]
    if all(parts) and len({(m.group(1), m.group(3)) for m in parts}) == 1:
        numbers = [int(m.group(2)) for m in parts]
        for a, b, na, nb in zip(numbers, numbers[1:], names, names[1:]):
            if b != a + 1:
                what = (f"{b - a - 1} frame(s) missing between {na} and {nb}" if b > a + 1 else
                        f"{na} and {nb} carry the same number")
                raise ImageFileError(f"{folder}: {what}; frames are consecutive files (their timestamps are "
                                     f"their positions)")
    return names


def still_sequence(location, start_index: int = -1, allow_outside: bool = False) -> StillSequence:
    """Open a raw still sequence (docs/BATCH.md, nrimagesrc): `location` a folder (its STILL_EXTENSIONS
    files of one kind, natural order: frame_2 before frame_10; the mask its camera.json names is not a
    frame) or a printf pattern (`dir/frame_%05d.tif`,
    from `start_index`, default the lowest index present). Checked before any frame is used: the files
    exist and are consecutive, lie in the folder (no link out of it, unless `allow_outside`), and every
    header is a single one-channel unsigned 16-bit image of the first file's size. Errors: ImageFileError
    naming the folder or file."""
    loc = str(location)
    if "%" in os.path.basename(loc):
        folder = Path(os.path.dirname(loc) or ".")
        if not folder.is_dir():
            raise ImageFileError(f"{folder}: no such folder (the folder of the pattern {loc})")
        if os.path.splitext(loc)[1].lower() not in STILL_EXTENSIONS:
            raise ImageFileError(f"{loc}: a still pattern ends in one of {', '.join(STILL_EXTENSIONS)}")
        names = _pattern_names(folder, os.path.basename(loc), int(start_index))
    elif os.path.isdir(loc):
        if start_index >= 0:
            raise ImageFileError(f"{loc}: start-index {start_index} is for a file pattern (frame_%05d.tif); a "
                                 f"folder's sequence is all its images")
        folder = Path(loc)
        names = _folder_names(folder)
    elif os.path.exists(loc):
        raise ImageFileError(f"{loc}: not a folder; a still sequence is a folder of images or a file pattern "
                             f"such as frame_%05d.tif")
    else:
        raise ImageFileError(f"{loc}: no such folder")
    files = [str(resolve_named(folder / n, "location", n, ImageFileError, allow_outside)) for n in names]
    h, w = still_size(files[0])
    for f in files[1:]:
        try:
            still_size(f, (h, w))
        except ImageSizeError as e:
            raise ImageSizeError(f"{e}: every frame of a sequence has the size of the first, {files[0]}") from None
    return StillSequence(loc, tuple(files), w, h)


class RawVideoWriter:
    """Append GRAY16_LE frames to a raw file (`filesrc ! rawvideoparse format=gray16-le`). The file is
    written to a temporary name and renamed on `close()`, so an interrupted run leaves no partial file."""

    def __init__(self, path, width: int, height: int):
        self.path, self._tmp = _atomic_target(path)
        self.width, self.height, self.frames = width, height, 0
        self._f = open(self._tmp, "wb")

    def write(self, frame: np.ndarray) -> None:
        f = np.asarray(frame)
        if f.shape != (self.height, self.width) or f.dtype != np.uint16:
            raise ValueError(f"{self.path}: frame must be uint16 {self.height}x{self.width}, "
                             f"got {f.dtype} {f.shape}")
        self._f.write(f.astype("<u2", copy=False).tobytes())
        self.frames += 1

    def close(self) -> Path:
        self._f.close()
        os.replace(self._tmp, self.path)
        return self.path

    def abort(self) -> None:
        self._f.close()
        self._tmp.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:
            self.abort()


def read_raw_video(path, width: int, height: int) -> np.ndarray:
    """Read a GRAY16_LE raw file as (frames, H, W) uint16 (memory-mapped); a trailing partial frame is an
    error naming the file."""
    if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))
            and width >= 1 and height >= 1):
        raise ImageFileError(f"{path}: frame size must be positive integers, got {width!r}x{height!r}")
    try:
        size = os.path.getsize(path)
    except OSError as e:
        raise ImageFileError(f"{path}: cannot read raw video: {e}") from None
    fb = width * height * 2
    if size == 0:
        return np.zeros((0, height, width), "<u2")
    if size % fb:
        raise ImageFileError(f"{path}: size {size} is not a whole number of {width}x{height} GRAY16_LE "
                             f"frames ({size // fb} frames + {size % fb} bytes)")
    return np.memmap(path, dtype="<u2", mode="r", shape=(size // fb, height, width))


# ======================================================================================================
# Outputs: never overwrite unless told, folders written as a whole
# ======================================================================================================

def refuse_existing(paths, hint: str = "--force") -> None:
    """Raise OutputExistsError naming the first of `paths` that exists (and how many do)."""
    existing = [Path(p) for p in paths if os.path.lexists(p)]
    if existing:
        more = f" (and {len(existing) - 1} more)" if len(existing) > 1 else ""
        raise OutputExistsError(f"{existing[0]} already exists{more}; nothing was written: use {hint} to "
                                f"replace it, or choose another output")


def owned_by_patterns(*patterns: str):
    """`owned(rel_path) -> bool` for `outputs.staged_folder`: True when the path relative to the output folder (posix
    form) fully matches one of the regular expressions."""
    rx = [re.compile(p) for p in patterns]
    return lambda rel: any(r.fullmatch(rel) for r in rx)
