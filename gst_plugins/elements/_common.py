"""Shared helpers of the nrhdr GStreamer elements: the HDR frame (`other/x-nrhdr`, docs/ARCHITECTURE.md),
error posting, string "enum" properties and profile loading.

Importing this module initialises GStreamer (idempotent) but compiles nothing: numba kernels are warmed up
in the elements' `do_start`.
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
import threading
import traceback

import gi

gi.require_version("Gst", "1.0")
gi.require_version("GstBase", "1.0")
gi.require_version("GstVideo", "1.0")
from gi.repository import GObject, Gst, GstBase, GstVideo  # noqa: E402

import numpy as np  # noqa: E402

if not Gst.is_initialized():
    Gst.init(None)

__all__ = ["Gst", "GstBase", "GstVideo", "GObject", "np", "HDR_MEDIA_TYPE", "hdr_template_caps",
           "HdrInfo", "alloc_hdr_buffer", "map_hdr", "map_video", "ErrorPoster", "Choice", "load_profile",
           "copy_timestamps", "MUTABLE_PLAYING", "MUTABLE_READY", "CONTROLLABLE"]

HDR_MEDIA_TYPE = "other/x-nrhdr"
_INT_RANGE = "(int)[1,2147483647]"
_FPS_RANGE = "(fraction)[0/1,2147483647/1]"

RW = Gst.MapFlags.READ | Gst.MapFlags.WRITE
MUTABLE_PLAYING = int(Gst.PARAM_MUTABLE_PLAYING)
MUTABLE_READY = int(Gst.PARAM_MUTABLE_READY)
CONTROLLABLE = int(Gst.PARAM_CONTROLLABLE)  # GstController curves (BaseTransform syncs them per frame)
PROP_RW = GObject.ParamFlags.READWRITE


def hdr_template_caps() -> Gst.Caps:
    return Gst.Caps.from_string(f"{HDR_MEDIA_TYPE}, width={_INT_RANGE}, height={_INT_RANGE}, "
                                f"framerate={_FPS_RANGE}")


def raw_template_caps(formats: str) -> Gst.Caps:
    return Gst.Caps.from_string(f"video/x-raw, format=(string){formats}, width={_INT_RANGE}, "
                                f"height={_INT_RANGE}, framerate={_FPS_RANGE}")


def copy_fields(src: Gst.Structure, dst: Gst.Structure, fields=("width", "height", "framerate")) -> None:
    for f in fields:
        if src.has_field(f):
            dst.set_value(f, src.get_value(f))


def transform_caps_by_structure(caps: Gst.Caps, filt: Gst.Caps | None, make, element=None) -> Gst.Caps:
    """Map each structure of `caps` with `make(structure) -> list[Gst.Structure]`, then intersect with the
    filter (first-caps order kept). An exception becomes an element error (if `element`) and empty caps,
    never a Python traceback with NULL caps."""
    try:
        out = Gst.Caps.new_empty()
        for i in range(caps.get_size()):
            for s in make(caps.get_structure(i)):
                out.append_structure(s)
        if filt is not None:
            out = filt.intersect_full(out, Gst.CapsIntersectMode.FIRST)
        return out
    except Exception as e:  # noqa: BLE001
        if element is not None:
            element.post_exception("transform_caps", e)
        return Gst.Caps.new_empty()


@dataclasses.dataclass(frozen=True)
class HdrInfo:
    """The fixed `other/x-nrhdr` caps of a stream."""
    width: int
    height: int
    fps_n: int
    fps_d: int
    white: float | None
    profile: str | None

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def size(self) -> int:
        return 5 * self.pixels

    @classmethod
    def from_caps(cls, caps: Gst.Caps) -> "HdrInfo":
        if caps is None or caps.get_size() < 1:
            raise ValueError("no caps")
        s = caps.get_structure(0)
        if s.get_name() != HDR_MEDIA_TYPE:
            raise ValueError(f"caps are {s.get_name()}, expected {HDR_MEDIA_TYPE}")
        okw, w = s.get_int("width")
        okh, h = s.get_int("height")
        if not (okw and okh) or w < 1 or h < 1:
            raise ValueError(f"{HDR_MEDIA_TYPE} caps without a fixed width/height: {caps.to_string()}")
        okf, fn, fd = s.get_fraction("framerate")
        if not okf:
            fn, fd = 0, 1
        white = None
        if s.has_field("white"):
            okwh, wv = s.get_double("white")
            if okwh and np.isfinite(wv) and wv > 0:
                white = float(wv)
        prof = s.get_string("profile") if s.has_field("profile") else None
        return cls(w, h, fn, fd, white, prof or None)


def _alloc_params():
    try:
        p = Gst.AllocationParams()
        p.align = 63
        return p
    except Exception:  # pragma: no cover - binding differences
        return None


_PARAMS = None


def alloc_hdr_buffer(width: int, height: int) -> Gst.Buffer:
    """A new HDR frame: block 0 float32 values (4*W*H bytes), block 1 uint8 state (W*H bytes)."""
    global _PARAMS
    if _PARAMS is None:
        _PARAMS = _alloc_params()
    n = width * height
    alloc = Gst.Allocator.find(None)
    buf = Gst.Buffer.new()
    buf.append_memory(alloc.alloc(4 * n, _PARAMS))
    buf.append_memory(alloc.alloc(n, _PARAMS))
    return buf


def check_hdr_buffer(buf: Gst.Buffer, info: HdrInfo) -> None:
    n = info.pixels
    if buf.n_memory() != 2:
        raise ValueError(f"buffer is not an nrhdr HDR frame: {buf.n_memory()} memory blocks, expected 2 "
                         f"(float32 values, uint8 state)")
    s0 = buf.peek_memory(0).get_sizes()[0]
    s1 = buf.peek_memory(1).get_sizes()[0]
    if s0 != 4 * n or s1 != n:
        raise ValueError(f"HDR frame blocks are {s0} and {s1} bytes; {info.width}x{info.height} needs "
                         f"{4 * n} and {n}")


@contextlib.contextmanager
def map_hdr(buf: Gst.Buffer, info: HdrInfo, write: bool):
    """Yield (values float32 (H, W), state uint8 (H, W)) views of an HDR frame's two memory blocks. The views
    are only valid inside the `with` block."""
    check_hdr_buffer(buf, info)
    flags = RW if write else Gst.MapFlags.READ
    shape = (info.height, info.width)
    ok0, m0 = buf.map_range(0, 1, flags)
    if not ok0:
        raise RuntimeError("cannot map the HDR values block" + (" for writing" if write else ""))
    try:
        ok1, m1 = buf.map_range(1, 1, flags)
        if not ok1:
            raise RuntimeError("cannot map the HDR state block" + (" for writing" if write else ""))
        try:
            yield (np.ndarray(shape, np.float32, buffer=m0.data), np.ndarray(shape, np.uint8, buffer=m1.data))
        finally:
            buf.unmap(m1)
    finally:
        buf.unmap(m0)


@contextlib.contextmanager
def map_video(buf: Gst.Buffer, vi: GstVideo.VideoInfo, dtype, write: bool):
    """Yield an (H, W) view of a single-plane gray video buffer. The row stride is the VideoInfo's when
    the buffer has the VideoInfo's size, else size / height (e.g. rawvideoparse plane-strides=<2*W>)."""
    dtype = np.dtype(dtype)
    h, w = vi.height, vi.width
    size = buf.get_size()
    if size == vi.size:
        stride, offset = vi.stride[0], vi.offset[0]
    elif h > 0 and size % h == 0 and size // h >= w * dtype.itemsize:
        stride, offset = size // h, 0
    else:
        raise ValueError(f"buffer of {size} bytes does not hold a {w}x{h} {vi.finfo.name} frame "
                         f"({vi.size} bytes expected)")
    ok, mi = buf.map(RW if write else Gst.MapFlags.READ)
    if not ok:
        raise RuntimeError("cannot map the video buffer" + (" for writing" if write else ""))
    try:
        yield np.ndarray((h, w), dtype, buffer=mi.data, offset=offset, strides=(stride, dtype.itemsize))
    finally:
        buf.unmap(mi)


def copy_timestamps(src: Gst.Buffer, dst: Gst.Buffer) -> None:
    dst.pts = src.pts
    dst.dts = src.dts
    dst.duration = src.duration
    dst.offset = src.offset
    dst.offset_end = src.offset_end
    if src.has_flags(Gst.BufferFlags.DISCONT):
        dst.set_flags(Gst.BufferFlags.DISCONT)


class ErrorPoster:
    """Mixin (plain Python, no vfuncs) for posting element errors that name the element and the problem.
    gst-launch prints them as `ERROR: from element /GstPipeline:pipeline0/GstNrValidity:nrvalidity0: <text>`."""

    def post_error(self, text: str, debug: str | None = None, kind: str = "stream") -> None:
        """Post an element error; the same text is posted once per run (upstream may retry a refused
        caps event several times). `reset_errors()` in do_start."""
        posted = self.__dict__.setdefault("_nr_posted", set())
        if text in posted:
            return
        posted.add(text)
        domains = {
            "stream": (Gst.stream_error_quark(), int(Gst.StreamError.FAILED)),
            "format": (Gst.stream_error_quark(), int(Gst.StreamError.FORMAT)),
            "settings": (Gst.resource_error_quark(), int(Gst.ResourceError.SETTINGS)),
            "read": (Gst.resource_error_quark(), int(Gst.ResourceError.READ)),
            "write": (Gst.resource_error_quark(), int(Gst.ResourceError.WRITE)),
            "not-found": (Gst.resource_error_quark(), int(Gst.ResourceError.NOT_FOUND)),
            "negotiation": (Gst.core_error_quark(), int(Gst.CoreError.NEGOTIATION)),
        }
        domain, code = domains.get(kind, domains["stream"])
        f = sys._getframe(1)
        if f.f_code.co_name == "post_exception" and f.f_back is not None:
            f = f.f_back
        self.message_full(Gst.MessageType.ERROR, domain, code, text, debug, f.f_code.co_filename,
                          f.f_code.co_name, f.f_lineno)

    def set_choice(self, choice: "Choice", value) -> str | None:
        """Validate a string-choice property value. Valid: store and return it. Invalid before start:
        remembered, so do_start fails with a clear element error. Invalid while PAUSED/PLAYING: ignored
        (the previous value stays) with a WARNING message on the bus. Returns None when not applied."""
        err = choice.check(value)
        if err is None:
            choice.invalid = None
            choice.value = str(value).strip().lower()
            return choice.value
        Gst.warning(f"{self.get_name()}: {err}")
        if self.get_state(0)[1] in (Gst.State.PAUSED, Gst.State.PLAYING):
            self.message_full(Gst.MessageType.WARNING, Gst.core_error_quark(), int(Gst.CoreError.FAILED),
                              f"{err}; keeping {choice.value!r}", None, __file__, "set_property", 0)
        else:
            choice.invalid = err
        return None

    def sync_controlled(self, buf) -> None:
        """Apply GstController curves of CONTROLLABLE properties at the buffer's stream time (BaseTransform
        leaves this to subclasses: call from do_before_transform)."""
        ts = buf.pts
        if ts == Gst.CLOCK_TIME_NONE:
            return
        st = self.segment.to_stream_time(Gst.Format.TIME, ts)
        if st != Gst.CLOCK_TIME_NONE:
            self.sync_values(st)

    def reset_errors(self) -> None:
        self.__dict__["_nr_posted"] = set()

    def post_exception(self, where: str, exc: BaseException) -> Gst.FlowReturn:
        """Post an element error for an exception raised in a vfunc and return FlowReturn.ERROR."""
        tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
        self.post_error(f"{where}: {type(exc).__name__}: {exc}", tb)
        return Gst.FlowReturn.ERROR


class Choice:
    """A string property restricted to a set of words (PyGObject 3.42 cannot register new GEnum types).
    `set(value)` returns None when valid, else an error text; an invalid value set before start is
    remembered so `do_start` fails with a clear element error instead of silently using a default."""

    def __init__(self, prop: str, choices, default: str):
        self.prop, self.choices, self.value, self.invalid = prop, tuple(choices), default, None

    def check(self, value) -> str | None:
        v = str(value).strip().lower() if value is not None else ""
        if v not in self.choices:
            return f"invalid value {value!r} for property '{self.prop}' (choose one of: {', '.join(self.choices)})"
        return None

    def blurb(self, text: str) -> str:
        return f"{text} (one of: {', '.join(self.choices)})"


# ---- profiles --------------------------------------------------------------------------------------

_profile_cache: dict = {}
_profile_lock = threading.Lock()


def load_profile(path: str):
    """nrhdr_core.profile.load with a small cache keyed by (absolute path, mtime, size); ProfileError
    propagates with its message naming the file and the field."""
    from nrhdr_core import profile as profile_mod
    if not path:
        raise profile_mod.ProfileError("no camera profile set (property 'profile' is empty)")
    ap = os.path.abspath(os.path.expanduser(path))
    try:
        st = os.stat(ap)
        key = (ap, st.st_mtime_ns, st.st_size)
    except OSError:
        key = None
    if key is not None:
        with _profile_lock:
            p = _profile_cache.get(key)
        if p is not None:
            return p
    p = profile_mod.load(ap)
    if key is not None:
        with _profile_lock:
            if len(_profile_cache) >= 8:
                _profile_cache.clear()
            _profile_cache[key] = p
    return p


# ---- live operation: QoS, processing latency, JIT reports (issue #7, helper "live") ----------------

import time  # noqa: E402

class LiveTiming:
    """Mixin for the processing BaseTransforms (docs/ELEMENTS.md "Live operation"):

    - QoS on by default (`qos` property of BaseTransform): late buffers are dropped before `transform`.
    - Per-frame processing time, measured between a sink-pad and a src-pad buffer probe, feeds a running
      estimate (`nrhdr_core.realtime.FrameTimes`); the LATENCY query answers upstream's latency plus
      that estimate, or the `processing-latency` property when >= 0; a LATENCY message is posted when
      the estimate grows by more than 25 %, so the pipeline recomputes its latency.
    - `nr_warmup(fn)`: run a core warm-up and report numba compilations (cache misses) with a Gst INFO
      log line and an element INFO message instead of stalling silently.

    A class opts in with `do_gst_base_transform_query = LiveTiming.nr_live_query`,
    `processing_latency = live_latency_property()` in its body and `self.nr_live_init()` in __init__."""

    def nr_live_init(self) -> None:
        from nrhdr_core.realtime import FrameTimes
        self.set_qos_enabled(True)
        self._nr_times = FrameTimes()
        self._nr_fixed_latency = -1.0      # ms; < 0 = the measured estimate
        self._nr_t0 = None
        self._nr_jit_seen = 0
        self._nr_in = self._nr_out = 0
        self.sinkpad.add_probe(Gst.PadProbeType.BUFFER, self._nr_sink_probe)
        self.srcpad.add_probe(Gst.PadProbeType.BUFFER, self._nr_src_probe)

    def _nr_sink_probe(self, pad, info):
        from nrhdr_core.realtime import JitWatch
        self._nr_in += 1
        self._nr_jit_seen = JitWatch.count
        self._nr_t0 = time.perf_counter()
        return Gst.PadProbeReturn.OK

    def _nr_src_probe(self, pad, info):
        t0, self._nr_t0 = self._nr_t0, None
        self._nr_out += 1
        if t0 is not None and self._nr_times.add(time.perf_counter() - t0) and self._nr_fixed_latency < 0:
            self.post_message(Gst.Message.new_latency(self))
        from nrhdr_core.realtime import JitWatch
        if t0 is not None and JitWatch.count != self._nr_jit_seen:  # compiled inside this frame's transform
            self._nr_report_jit("while streaming", self._nr_jit_seen)
        return Gst.PadProbeReturn.OK

    def _nr_report_jit(self, when, seen):
        from nrhdr_core.realtime import JitWatch
        n, sec, names = JitWatch.since((seen, JitWatch.seconds))
        text = (f"{self.get_name()}: numba compiled {n} function(s) {when} (not in the numba cache: run "
                f"'nrhdr warmup' once after install or after a source change)"
                + (f": {', '.join(names)}" if names else ""))
        Gst.info(text)
        self.message_full(Gst.MessageType.INFO, Gst.core_error_quark(), int(Gst.CoreError.FAILED), text,
                          text, __file__, "nr_live", 0)  # gst-launch prints an INFO's debug text only

    def nr_live_reset(self) -> None:
        self._nr_times.reset()
        self._nr_in = self._nr_out = 0

    def nr_qos_skipped(self) -> int:
        """Buffers that entered and were not pushed (dropped by QoS), the one in flight excluded."""
        return max(self._nr_in - self._nr_out - (1 if self._nr_t0 is not None else 0), 0)

    def nr_processing_latency(self) -> int:
        """Nanoseconds this element adds to the pipeline latency."""
        ms = self._nr_fixed_latency
        sec = ms / 1e3 if ms >= 0 else self._nr_times.estimate()
        return int(sec * Gst.SECOND)

    def nr_live_query(self, direction, query):
        ok = GstBase.BaseTransform.do_query(self, direction, query)
        if ok and query.type == Gst.QueryType.LATENCY and direction == Gst.PadDirection.SRC:
            live, lo, hi = query.parse_latency()
            own = self.nr_processing_latency()
            query.set_latency(live, lo + own, hi if hi == Gst.CLOCK_TIME_NONE else hi + own)
        return ok

    def nr_warmup(self, fn, *args, **kw):
        """Call a core warm-up; report numba compilations it caused (a cache miss: `nrhdr warmup`)."""
        from nrhdr_core.realtime import JitWatch
        snap = JitWatch.snapshot()
        t0 = time.perf_counter()
        out = fn(*args, **kw)
        if JitWatch.count != snap[0]:
            self._nr_report_jit(f"at start in {time.perf_counter() - t0:.1f} s", snap[0])
        return out


def live_latency_property():
    """The `processing-latency` property of LiveTiming elements (ms, -1 = measured)."""
    def getter(self):
        return self._nr_fixed_latency

    def setter(self, value):
        self._nr_fixed_latency = float(value)
        self.post_message(Gst.Message.new_latency(self))

    return GObject.Property(type=float, default=-1.0, minimum=-1.0, maximum=60000.0,
                            nick="Processing latency",
                            blurb="Milliseconds this element adds to the pipeline latency (LATENCY query); "
                                  "-1 = a running estimate (95th percentile of the last 32 frames x 1.2), "
                                  "posting a LATENCY message when it grows by more than 25 %",
                            flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING, getter=getter, setter=setter)
