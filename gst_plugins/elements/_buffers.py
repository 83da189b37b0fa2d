"""Buffers of the elements: the HDR frame's buffer pool and allocation, mapping HDR and gray video
buffers as numpy views (no copy), the one-buffer-one-frame size checks, and timestamp copies."""
from __future__ import annotations

import contextlib

from ._caps import LAYOUT_CHANNELS, LAYOUTS, HdrInfo
from ._gst import Gst, GstVideo, np

RW = Gst.MapFlags.READ | Gst.MapFlags.WRITE


class FrameSizeError(ValueError):
    """A buffer that does not hold exactly one frame of the negotiated caps."""


def _alloc_params():
    try:
        p = Gst.AllocationParams()
        p.align = 63                     # 64-byte aligned: the float32 plane starts on a cache line
        return p
    except Exception:  # pragma: no cover - binding differences
        return None


_PARAMS = None


def _params():
    global _PARAMS
    if _PARAMS is None:
        _PARAMS = _alloc_params()
    return _PARAMS


def alloc_hdr_buffer(width: int, height: int, channels: int = 1) -> Gst.Buffer:
    """A new HDR frame: ONE memory block of (4*channels+1)*W*H bytes (float32 values, `channels` planes,
    then uint8 state). Elements use `HdrPool` instead (allocated once per size); this is for apps and tests."""
    if channels not in (1, 3):
        raise ValueError(f"an HDR frame has 1 or 3 float planes, not {channels}")
    return Gst.Buffer.new_allocate(Gst.Allocator.find(None), (4 * channels + 1) * width * height, _params())


class HdrPool:
    """A Gst.BufferPool of one-block HDR frames of one size: buffers are allocated once and come back to
    the pool when downstream releases them (no allocation per frame). Rebuilt by `for_info` when the size
    changes (renegotiation)."""

    def __init__(self, info: HdrInfo, min_buffers: int = 2):
        self.size = info.size
        self.pool = Gst.BufferPool.new()
        cfg = self.pool.get_config()
        caps = Gst.Caps.from_string(info.replace(fps_n=0, fps_d=0).caps_string())
        Gst.BufferPool.config_set_params(cfg, caps, self.size, min_buffers, 0)
        p = _params()
        if p is not None:
            Gst.BufferPool.config_set_allocator(cfg, None, p)
        if not self.pool.set_config(cfg) or not self.pool.set_active(True):
            raise RuntimeError(f"cannot set up a buffer pool of {self.size}-byte HDR frames")

    @classmethod
    def for_info(cls, old: "HdrPool | None", info: HdrInfo) -> "HdrPool":
        if old is not None and old.size == info.size:
            return old
        if old is not None:
            old.close()
        return cls(info)

    def acquire(self) -> Gst.Buffer:
        ret, buf = self.pool.acquire_buffer(None)
        if ret != Gst.FlowReturn.OK or buf is None:
            raise RuntimeError(f"buffer pool gave no HDR frame ({ret.value_nick if ret else ret})")
        return buf

    def close(self) -> None:
        try:
            self.pool.set_active(False)
        except Exception:  # noqa: BLE001
            pass


def check_hdr_buffer(buf: Gst.Buffer, info: HdrInfo) -> None:
    """Raise FrameSizeError unless `buf` holds exactly one frame of `info` ((4*channels+1)*W*H bytes)."""
    size = buf.get_size()
    if size != info.size:
        c = info.channels
        planes = "4*W*H float32 values" if c == 1 else f"{c} planes of 4*W*H float32 values (R, G, B)"
        other = [lay for lay, k in LAYOUT_CHANNELS.items() if lay != info.layout and size == (4 * k + 1) * info.pixels]
        hint = f" ({size} bytes is one {other[0]} frame: check the caps' layout)" if other else ""
        raise FrameSizeError(
            f"buffer is not an nrhdr HDR frame: {size} bytes in {buf.n_memory()} memory block(s), expected "
            f"{info.size} bytes for one {info.width}x{info.height} {info.layout} frame ({planes} "
            f"then W*H state bytes){hint}. Reading a raw HDR recording? Use filesrc blocksize={info.size}")


@contextlib.contextmanager
def map_hdr(buf: Gst.Buffer, info: HdrInfo, write: bool):
    """Yield (values float32 (H, W), or (3, H, W) for a colour frame (planes R, G, B), state uint8 (H, W)):
    numpy views into the mapped frame, no copy (read-only arrays unless `write`). Valid only inside the
    `with` block.

    Frames made by the nrhdr elements are one contiguous block, mapped in place. A buffer of several
    blocks (e.g. a depayloader's output) is merged by GStreamer's map into one block of the same layout (a
    copy, made once). A frame whose float plane is not 4-byte aligned (bytes from a file or network) is
    read through an aligned copy (written back when `write`)."""
    check_hdr_buffer(buf, info)
    ok, mi = buf.map(RW if write else Gst.MapFlags.READ)
    if not ok:
        raise RuntimeError("cannot map the HDR frame" + (" for writing (buffer not writable)" if write else ""))
    try:
        shape = info.shape
        raw = np.frombuffer(mi.data, np.uint8, count=info.size)
        state = raw[info.state_offset:].reshape(info.height, info.width)
        if raw.ctypes.data % 4 == 0:
            yield raw[:info.state_offset].view(np.float32).reshape(shape), state
        else:
            values = raw[:info.state_offset].copy().view(np.float32).reshape(shape)
            yield values, state
            if write:
                raw[:info.state_offset] = values.reshape(-1).view(np.uint8)
    finally:
        buf.unmap(mi)


@contextlib.contextmanager
def map_sample(sample, write: bool = False):
    """For apps (appsink): yield (values, state) numpy views of an `other/x-nrhdr` Gst.Sample's frame (values
    (H, W), or (3, H, W) for a colour frame), no copy; valid inside the `with` block only (copy what you keep).
    examples/appsink_numpy.py."""
    info = HdrInfo.from_caps(sample.get_caps(), LAYOUTS)
    with map_hdr(sample.get_buffer(), info, write) as planes:
        yield planes


def video_layout(buf: Gst.Buffer, vi: GstVideo.VideoInfo) -> tuple[int, int, int, bool]:
    """(offset, row stride, expected bytes, from_meta) of a single-plane gray frame in `buf`: the buffer's
    GstVideoMeta when it has one (rawvideoparse plane-strides / plane-offsets), else the caps' VideoInfo."""
    meta = None
    try:
        meta = GstVideo.buffer_get_video_meta(buf)
    except Exception:  # noqa: BLE001 - no usable meta: the caps' layout
        meta = None
    if meta is not None:
        off, stride = int(meta.offset[0]), int(meta.stride[0])
        return off, stride, off + stride * vi.height, True
    return int(vi.offset[0]), int(vi.stride[0]), int(vi.size), False


def check_video_buffer(buf: Gst.Buffer, vi: GstVideo.VideoInfo, exact: bool = True) -> tuple[int, int]:
    """(offset, stride) of the one frame in `buf`; FrameSizeError when the buffer does not hold exactly
    one frame of the caps (a buffer of two frames is refused, never read as one frame of wider rows).
    `exact=False` (an output buffer from downstream's pool): larger buffers are fine."""
    off, stride, expected, from_meta = video_layout(buf, vi)
    size = buf.get_size()
    w, h = vi.width, vi.height
    row = w * vi.finfo.pixel_stride[0] if vi.finfo.pixel_stride[0] > 0 else w
    # with a video meta the last row may end at its pixels (no padding after it)
    least = off + stride * (h - 1) + row if from_meta else expected
    if size < least or (exact and size > expected) or stride < row:
        layout = (f"rows of {stride} bytes at offset {off} (video meta)" if from_meta else
                  f"rows of {stride} bytes")
        raise FrameSizeError(
            f"buffer of {size} bytes does not hold exactly one {w}x{h} {vi.finfo.name} frame: expected "
            f"{expected} bytes ({layout}), received {size}; every buffer must hold one frame of the "
            f"negotiated caps (check the source's frame size, e.g. rawvideoparse width/height/frame-size/"
            f"plane-strides)")
    return off, stride


@contextlib.contextmanager
def map_video(buf: Gst.Buffer, vi: GstVideo.VideoInfo, dtype, write: bool, exact: bool = True):
    """Yield an (H, W) view of a single-plane gray video buffer holding exactly one frame (row stride and
    offset from its GstVideoMeta, else from the caps); FrameSizeError otherwise."""
    dtype = np.dtype(dtype)
    off, stride = check_video_buffer(buf, vi, exact)
    ok, mi = buf.map(RW if write else Gst.MapFlags.READ)
    if not ok:
        raise RuntimeError("cannot map the video buffer" + (" for writing" if write else ""))
    try:
        yield np.ndarray((vi.height, vi.width), dtype, buffer=mi.data, offset=off,
                         strides=(stride, dtype.itemsize))
    finally:
        buf.unmap(mi)


# the flags that describe a frame's place in the stream (not its memory): carried from input to output frame
_STREAM_FLAGS = tuple(getattr(Gst.BufferFlags, n) for n in (
    "LIVE", "DECODE_ONLY", "DISCONT", "RESYNC", "CORRUPTED", "MARKER", "HEADER", "GAP", "DROPPABLE", "DELTA_UNIT",
    "SYNC_AFTER", "NON_DROPPABLE") if hasattr(Gst.BufferFlags, n))


def copy_timestamps(src: Gst.Buffer, dst: Gst.Buffer) -> None:
    """PTS, DTS, duration, offsets and the stream flags (DISCONT, GAP, DELTA_UNIT...) of `src` onto a new
    output frame `dst`."""
    dst.pts = src.pts
    dst.dts = src.dts
    dst.duration = src.duration
    dst.offset = src.offset
    dst.offset_end = src.offset_end
    for flag in _STREAM_FLAGS:
        if src.has_flags(flag):
            dst.set_flags(flag)


def gray16_buffer(vi: GstVideo.VideoInfo, frame: np.ndarray, index: int, pts: int, duration: int) -> Gst.Buffer:
    """A new GRAY16_LE buffer holding `frame` (uint16 (H, W)) at the caps' row stride, with PTS, duration and
    offsets of frame `index` (no DTS): what the raw sources push."""
    buf = Gst.Buffer.new_allocate(None, vi.size, None)
    ok, mi = buf.map(Gst.MapFlags.WRITE)
    if not ok:
        raise RuntimeError("cannot map a new buffer for writing")
    try:
        dst = np.ndarray((vi.height, vi.width), "<u2", buffer=mi.data, offset=vi.offset[0],
                         strides=(vi.stride[0], 2))
        np.copyto(dst, frame)
    finally:
        buf.unmap(mi)
    buf.pts = pts
    buf.dts = Gst.CLOCK_TIME_NONE
    buf.duration = duration
    buf.offset = index
    buf.offset_end = index + 1
    return buf
