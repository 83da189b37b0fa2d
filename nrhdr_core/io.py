"""Image and video files: OpenImageIO for images (PNG, TIFF, OpenEXR, Radiance .hdr), numpy for raw video.

Every writer is atomic: it writes to a temporary file beside the target and renames it, so a file is
written completely or not at all.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

# Rec. 709 / sRGB luminance weights for linear RGB.
LUMA_709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)


class ImageFileError(ValueError):
    """A file could not be read or has unexpected content; the message names the file."""


def _oiio():
    import OpenImageIO as oiio  # imported lazily: keeps `import nrhdr_core` light
    return oiio


def read_image(path, dtype=np.float32) -> np.ndarray:
    """Read any image OpenImageIO supports as (H, W, C) array of `dtype` (float: values as stored for
    float files, 0..1 for integer files; uint8/uint16: native codes)."""
    oiio = _oiio()
    path = str(path)
    if not os.path.isfile(path):
        raise ImageFileError(f"{path}: no such file")
    buf = oiio.ImageBuf(path)
    if buf.has_error:
        raise ImageFileError(f"{path}: cannot read image: {buf.geterror()}")
    fmt = {np.dtype(np.float32): oiio.FLOAT, np.dtype(np.uint8): oiio.UINT8,
           np.dtype(np.uint16): oiio.UINT16, np.dtype(np.float64): oiio.DOUBLE}[np.dtype(dtype)]
    px = buf.get_pixels(fmt)
    if buf.has_error or px is None:
        raise ImageFileError(f"{path}: cannot decode pixels: {buf.geterror()}")
    px = np.asarray(px)
    if px.ndim == 2:
        px = px[:, :, None]
    return px


def read_luminance(path) -> np.ndarray:
    """Read an HDR (or LDR) image as linear luminance float32 (H, W).

    RGB(A) is converted with Rec. 709 weights; negative values (present in some EXR scenes) are clamped
    to 0; NaN/Inf are replaced by 0 (NaN) or the largest finite value (+Inf) and counted in the error
    message only if nothing finite is left."""
    px = read_image(path, np.float32).astype(np.float64)
    c = px.shape[2]
    if c >= 3:
        lum = px[:, :, :3] @ LUMA_709
    else:
        lum = px[:, :, 0]
    finite = np.isfinite(lum)
    if not finite.any():
        raise ImageFileError(f"{path}: no finite pixel values")
    if not finite.all():
        big = float(np.max(lum[finite]))
        lum = np.where(np.isnan(lum), 0.0, lum)
        lum = np.where(np.isposinf(lum), big, lum)
        lum = np.where(np.isneginf(lum), 0.0, lum)
    return np.maximum(lum, 0.0).astype(np.float32)


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


def write_exr(path, values, state=None) -> Path:
    """Write a linear HDR frame as OpenEXR (float32 channel "Y"); with `state`, a second channel "state"
    keeps the per-pixel validity state (docs/ARCHITECTURE.md) so a recording loses nothing."""
    v = np.asarray(values, dtype=np.float32)
    if state is None:
        return write_image(path, v, np.float32, ["Y"])
    both = np.stack([v, np.asarray(state, dtype=np.float32)], axis=-1)
    return write_image(path, both, np.float32, ["Y", "state"])


def read_exr(path):
    """Read an EXR written by `write_exr`: returns (values float32 (H, W), state uint8 (H, W) or None)."""
    oiio = _oiio()
    buf = oiio.ImageBuf(str(path))
    if buf.has_error:
        raise ImageFileError(f"{path}: cannot read: {buf.geterror()}")
    names = list(buf.spec().channelnames)
    px = np.asarray(buf.get_pixels(oiio.FLOAT))
    if px.ndim == 2:
        px = px[:, :, None]
    vi = names.index("Y") if "Y" in names else 0
    state = px[:, :, names.index("state")].astype(np.uint8) if "state" in names else None
    return px[:, :, vi].copy(), state


def write_mask(path, mask) -> Path:
    """Write an ND mask as 8-bit PNG, 255 = attenuated."""
    return write_image(path, np.where(np.asarray(mask, bool), 255, 0).astype(np.uint8), np.uint8)


def read_mask(path) -> np.ndarray:
    """Read an ND mask PNG (8-bit, one channel or equal channels; 255 = attenuated, 0 = regular)."""
    px = read_image(path, np.uint8)
    m = px[:, :, 0]
    if px.shape[2] > 1 and not all(np.array_equal(m, px[:, :, c]) for c in range(1, min(3, px.shape[2]))):
        raise ImageFileError(f"{path}: mask must be gray (all colour channels equal)")
    bad = (m != 0) & (m != 255)
    if bad.any():
        raise ImageFileError(f"{path}: mask must contain only 0 (regular) and 255 (attenuated); "
                             f"found {int(bad.sum())} other values, e.g. {int(m[bad][0])}")
    return m == 255


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
    size = os.path.getsize(path)
    fb = width * height * 2
    if size % fb:
        raise ImageFileError(f"{path}: size {size} is not a whole number of {width}x{height} GRAY16_LE "
                             f"frames ({size // fb} frames + {size % fb} bytes)")
    return np.memmap(path, dtype="<u2", mode="r", shape=(size // fb, height, width))
