"""Shared helpers of the nrhdr GStreamer elements: the HDR frame (`other/x-nrhdr`, one contiguous block,
docs/ARCHITECTURE.md), its buffer pool, error posting, GStreamer debug categories, Python warnings as bus
WARNING messages, string "enum" properties and profile loading.

Importing this module initialises GStreamer (idempotent, at the end of the module) but compiles nothing: numba kernels are warmed up
in the elements' `do_start`.
"""
from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import os
import sys
import threading
import traceback
import warnings

import gi

gi.require_version("Gst", "1.0")
gi.require_version("GstBase", "1.0")
gi.require_version("GstVideo", "1.0")
from gi.repository import GObject, Gst, GstBase, GstVideo  # noqa: E402

import numpy as np  # noqa: E402

__all__ = ["Gst", "GstBase", "GstVideo", "GObject", "np", "HDR_MEDIA_TYPE", "HDR_LAYOUT", "hdr_template_caps",
           "HdrInfo", "HdrPool", "alloc_hdr_buffer", "map_hdr", "map_sample", "map_video", "ErrorPoster", "Choice",
           "load_profile", "copy_timestamps", "debug_category", "MUTABLE_PLAYING", "MUTABLE_READY",
           "CONTROLLABLE"]

HDR_MEDIA_TYPE = "other/x-nrhdr"
# The one frame layout: float32 values (4*W*H bytes, row-major, no padding) then uint8 state (W*H bytes),
# in one contiguous buffer of 5*W*H bytes. Caps without a `layout` field mean this layout too.
HDR_LAYOUT = "f32-u8-planar"
# Fields a video stream keeps through the chain (raw -> HDR -> display).
STREAM_FIELDS = ("width", "height", "framerate", "pixel-aspect-ratio", "interlace-mode")
_INT_RANGE = "(int)[1,2147483647]"
_FPS_RANGE = "(fraction)[0/1,2147483647/1]"

RW = Gst.MapFlags.READ | Gst.MapFlags.WRITE
MUTABLE_PLAYING = int(Gst.PARAM_MUTABLE_PLAYING)
MUTABLE_READY = int(Gst.PARAM_MUTABLE_READY)
CONTROLLABLE = int(Gst.PARAM_CONTROLLABLE)  # GstController curves (BaseTransform syncs them per frame)
PROP_RW = GObject.ParamFlags.READWRITE


def hdr_template_caps(strict: bool = False) -> Gst.Caps:
    """`other/x-nrhdr, layout=(string)f32-u8-planar, width, height, framerate`. Unless `strict`, a second
    structure without `layout` accepts older caps (same layout: the field's absence means f32-u8-planar)."""
    body = f"width={_INT_RANGE}, height={_INT_RANGE}, framerate={_FPS_RANGE}"
    text = f"{HDR_MEDIA_TYPE}, layout=(string){HDR_LAYOUT}, {body}"
    if not strict:
        text += f"; {HDR_MEDIA_TYPE}, {body}"
    return Gst.Caps.from_string(text)


def raw_template_caps(formats: str) -> Gst.Caps:
    return Gst.Caps.from_string(f"video/x-raw, format=(string){formats}, width={_INT_RANGE}, "
                                f"height={_INT_RANGE}, framerate={_FPS_RANGE}")


def copy_fields(src: Gst.Structure, dst: Gst.Structure, fields=STREAM_FIELDS) -> None:
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
    diffuse_white: float | None = None   # regular pixels' white (caps field diffuse-white), nrvalidity
    layout: str = HDR_LAYOUT

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def size(self) -> int:
        """Bytes of one frame: 4*W*H float32 values then W*H state bytes."""
        return 5 * self.pixels

    @property
    def state_offset(self) -> int:
        return 4 * self.pixels

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
        if s.has_field("layout"):
            layout = s.get_string("layout")
            if layout != HDR_LAYOUT:
                raise ValueError(f"{HDR_MEDIA_TYPE} layout {layout!r} is not supported (only {HDR_LAYOUT}: "
                                 f"float32 values then uint8 state, one block)")

        def positive(field):
            if s.has_field(field):
                ok, v = s.get_double(field)
                if ok and np.isfinite(v) and v > 0:
                    return float(v)
            return None

        prof = s.get_string("profile") if s.has_field("profile") else None
        return cls(w, h, fn, fd, positive("white"), prof or None, positive("diffuse-white"))


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


def alloc_hdr_buffer(width: int, height: int) -> Gst.Buffer:
    """A new HDR frame: ONE memory block of 5*W*H bytes (float32 values, then uint8 state). Elements use
    `HdrPool` instead (allocated once per size); this is for apps and tests."""
    return Gst.Buffer.new_allocate(Gst.Allocator.find(None), 5 * width * height, _params())


class HdrPool:
    """A Gst.BufferPool of one-block HDR frames of one size: buffers are allocated once and come back to
    the pool when downstream releases them (no allocation per frame). Rebuilt by `for_info` when the size
    changes (renegotiation)."""

    def __init__(self, info: "HdrInfo", min_buffers: int = 2):
        self.size = info.size
        self.pool = Gst.BufferPool.new()
        cfg = self.pool.get_config()
        caps = Gst.Caps.from_string(f"{HDR_MEDIA_TYPE}, layout=(string){HDR_LAYOUT}, width=(int){info.width}, "
                                    f"height=(int){info.height}")
        Gst.BufferPool.config_set_params(cfg, caps, self.size, min_buffers, 0)
        p = _params()
        if p is not None:
            Gst.BufferPool.config_set_allocator(cfg, None, p)
        if not self.pool.set_config(cfg) or not self.pool.set_active(True):
            raise RuntimeError(f"cannot set up a buffer pool of {self.size}-byte HDR frames")

    @classmethod
    def for_info(cls, old: "HdrPool | None", info: "HdrInfo") -> "HdrPool":
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
    size = buf.get_size()
    if size != info.size:
        raise ValueError(
            f"buffer is not an nrhdr HDR frame: {size} bytes in {buf.n_memory()} memory block(s); a "
            f"{info.width}x{info.height} {HDR_LAYOUT} frame is {info.size} bytes (4*W*H float32 values then "
            f"W*H state bytes). Reading a raw HDR recording? Use filesrc blocksize={info.size}")


@contextlib.contextmanager
def map_hdr(buf: Gst.Buffer, info: HdrInfo, write: bool):
    """Yield (values float32 (H, W), state uint8 (H, W)): numpy views into the mapped frame, no copy
    (read-only arrays unless `write`). Valid only inside the `with` block.

    Frames made by the nrhdr elements are one contiguous block, mapped in place. A buffer of several
    blocks (the older two-block frames, or a depayloader's output) is merged by GStreamer's map into one
    block of the same layout (a copy, made once). A frame whose float plane is not 4-byte aligned (bytes
    from a file or network) is read through an aligned copy (written back when `write`)."""
    check_hdr_buffer(buf, info)
    ok, mi = buf.map(RW if write else Gst.MapFlags.READ)
    if not ok:
        raise RuntimeError("cannot map the HDR frame" + (" for writing (buffer not writable)" if write else ""))
    try:
        shape = (info.height, info.width)
        raw = np.frombuffer(mi.data, np.uint8, count=info.size)
        state = raw[info.state_offset:].reshape(shape)
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
    """For apps (appsink): yield (values, state) numpy views of an `other/x-nrhdr` Gst.Sample's frame, no
    copy; valid inside the `with` block only (copy what you keep). examples/appsink_numpy.py."""
    info = HdrInfo.from_caps(sample.get_caps())
    with map_hdr(sample.get_buffer(), info, write) as planes:
        yield planes


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


# ---- GStreamer debug categories ------------------------------------------------------------------------
# PyGObject 3.42 / gst-python 1.22 expose Gst.debug_log_literal (takes a Gst.DebugCategory) but no way to
# create a category (Gst.DebugCategory has no constructor, GST_DEBUG_CATEGORY_INIT is a C macro); the
# gst-python helpers Gst.debug()/Gst.log() all log to the single category "python". So the category is
# created with `_gst_debug_category_new` (the public ABI symbol behind GST_DEBUG_CATEGORY_INIT) through
# ctypes and then looked up as a Gst.DebugCategory. `GST_DEBUG=nrreconstruct:6` then works as for C
# elements; without libgstreamer reachable by ctypes, lines go to the "python" category.

_cat_lock = threading.Lock()
_categories: dict = {}


def debug_category(name: str, description: str):
    """The Gst.DebugCategory `name` (created once, thresholds from GST_DEBUG applied), or None."""
    with _cat_lock:
        if name in _categories:
            return _categories[name]
        cat = None
        try:
            for c in Gst.debug_get_all_categories():
                if c.get_name() == name:
                    cat = c
                    break
            if cat is None:
                lib = ctypes.CDLL("libgstreamer-1.0.so.0")
                new = lib._gst_debug_category_new
                new.restype = ctypes.c_void_p
                new.argtypes = [ctypes.c_char_p, ctypes.c_uint, ctypes.c_char_p]
                new(name.encode(), 0, description.encode())
                cat = next((c for c in Gst.debug_get_all_categories() if c.get_name() == name), None)
        except Exception:  # noqa: BLE001 - fall back to Gst.debug() & co. (category "python")
            cat = None
        _categories[name] = cat
        return cat


_PY_LOGGERS = {}


def _py_logger(level):
    if not _PY_LOGGERS:
        _PY_LOGGERS.update({Gst.DebugLevel.ERROR: Gst.error, Gst.DebugLevel.WARNING: Gst.warning,
                            Gst.DebugLevel.FIXME: Gst.fixme, Gst.DebugLevel.INFO: Gst.info,
                            Gst.DebugLevel.DEBUG: Gst.debug, Gst.DebugLevel.LOG: Gst.log,
                            Gst.DebugLevel.TRACE: Gst.trace})
    return _PY_LOGGERS.get(level, Gst.debug)


# ---- Python warnings raised inside an element -> bus WARNING messages -------------------------------------
# warnings.catch_warnings() is process-global, not per thread (elements run in several streaming threads),
# so a hook on warnings._showwarnmsg (which catch_warnings, pytest's included, does not replace) looks up the
# element running in the current thread and posts the warning on the bus; outside an element the usual
# display happens unchanged. The warning filters are left alone: their "default" action shows a warning once
# per location, and each element start (reset_errors) invalidates that memory, so every run reports it.

_tls = threading.local()
_HOOK_MARK = "_nrhdr_bus_hook"


def _install_warning_hook() -> None:
    prev = getattr(warnings, "_showwarnmsg", None)
    if prev is None or getattr(prev, _HOOK_MARK, False):
        return

    def hook(msg):
        el = getattr(_tls, "element", None)
        if el is not None:
            try:
                el.post_python_warning(msg)
                return
            except Exception:  # noqa: BLE001 - never lose the warning
                pass
        prev(msg)

    setattr(hook, _HOOK_MARK, True)
    warnings._showwarnmsg = hook


def _rearm_warnings() -> None:
    """Forget which warnings were already shown ("default"/"module" actions), as on a filter change."""
    f = getattr(warnings, "_filters_mutated", None)
    if f is not None:
        try:
            f()
        except Exception:  # noqa: BLE001
            pass


@contextlib.contextmanager
def _warnings_to(element):
    """Within the block, warnings raised in this thread become bus WARNING messages of `element`."""
    _install_warning_hook()
    old = getattr(_tls, "element", None)
    _tls.element = element
    try:
        yield
    finally:
        _tls.element = old


class ErrorPoster:
    """Mixin (plain Python, no vfuncs) for posting element errors that name the element and the problem.
    gst-launch prints them as `ERROR: from element /GstPipeline:pipeline0/GstNrValidity:nrvalidity0: <text>`.

    Also GStreamer debug logging in the element's own category (class attribute DEBUG_CATEGORY, made with
    `debug_category(factory, description)`): `self.gst_debug(text)`, `gst_log`, `gst_info`, `gst_warn`,
    `gst_trace`, `gst_debug_enabled(level)`; and `with self.warnings_to_bus():` around core calls."""

    DEBUG_CATEGORY = None

    def gst_debug_enabled(self, level=Gst.DebugLevel.LOG) -> bool:
        cat = type(self).DEBUG_CATEGORY
        if cat is None:
            return Gst.debug_is_active()
        return int(cat.get_threshold()) >= int(level)

    def _gst_log_at(self, level, text: str) -> None:
        cat = type(self).DEBUG_CATEGORY
        try:
            if cat is None:
                _py_logger(level)(f"{self.get_name()}: {text}")
                return
            if int(cat.get_threshold()) < int(level):
                return
            f = sys._getframe(2)
            Gst.debug_log_literal(cat, level, f.f_code.co_filename, f.f_code.co_name, f.f_lineno, self, text)
        except Exception:  # noqa: BLE001 - logging never breaks the stream
            pass

    def gst_warn(self, text: str) -> None:
        self._gst_log_at(Gst.DebugLevel.WARNING, text)

    def gst_info(self, text: str) -> None:
        self._gst_log_at(Gst.DebugLevel.INFO, text)

    def gst_debug(self, text: str) -> None:
        self._gst_log_at(Gst.DebugLevel.DEBUG, text)

    def gst_log(self, text: str) -> None:
        self._gst_log_at(Gst.DebugLevel.LOG, text)

    def gst_trace(self, text: str) -> None:
        self._gst_log_at(Gst.DebugLevel.TRACE, text)

    def warnings_to_bus(self):
        """Context manager: Python warnings raised in this thread inside the block (e.g. 'no pixel is
        known' from nrhdr_core) become bus WARNING messages from this element, each distinct text once
        per run (later repeats: DEBUG lines)."""
        return _warnings_to(self)

    def post_python_warning(self, msg) -> None:
        text = f"{msg.category.__name__}: {msg.message}"
        seen = self.__dict__.setdefault("_nr_warned", {})
        seen[text] = seen.get(text, 0) + 1
        if seen[text] > 1:
            self.gst_debug(f"warning repeated ({seen[text]} times): {text}")
            return
        self.gst_warn(text)
        self.message_full(Gst.MessageType.WARNING, Gst.stream_error_quark(), int(Gst.StreamError.FAILED),
                          text, f"{msg.filename}:{msg.lineno}", msg.filename or "", "warning",
                          int(msg.lineno or 0))

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
        self.gst_warn(err)
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
        self.__dict__["_nr_warned"] = {}
        _rearm_warnings()          # a new run reports Python warnings again

    def post_exception(self, where: str, exc: BaseException) -> Gst.FlowReturn:
        """Post an element error for an exception raised in a vfunc and return FlowReturn.ERROR."""
        tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
        self.gst_debug(f"{where}: {type(exc).__name__}: {exc}")
        self.post_error(f"{where}: {type(exc).__name__}: {exc}", tb)
        return Gst.FlowReturn.ERROR


class Choice:
    """A string property restricted to a set of words. PyGObject 3.42 does not register GEnum types from
    Python: a `class Mode(GObject.GEnum)` subclass keeps the abstract GType `GEnum`, and
    `GObject.Property(type=Mode)` fails with "could not get typecode from object" (checked on this
    platform, docs/ELEMENTS.md), so choices are strings validated here.
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
# Initialise GStreamer last, when every name above exists: with GST_REGISTRY_FORK=no (apps in a venv) the
# registry scan runs inside this call, in this process, and the plugin loader then imports the element
# shims, which import this module; done at the top, they found it half-initialised, failed, and the python
# plugin was cached in the registry with no elements (the registry-cache trap, docs/ELEMENTS.md).
if not Gst.is_initialized():
    Gst.init(None)
