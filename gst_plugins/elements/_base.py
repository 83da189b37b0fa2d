"""The skeleton every nrhdr element shares (`NrElement`): the property table, element errors that name the
element and the problem, debug logging, vfuncs whose exceptions become element errors, and the floating
reference GStreamer expects from a newly made element."""
from __future__ import annotations

import ctypes
import functools
import sys
import traceback

from ._buffers import FrameSizeError
from ._caps import CapsError
from ._gst import Gst
from ._log import Logging, rearm_warnings
from ._props import Properties

_ERROR_KINDS = {
    "stream": (Gst.stream_error_quark, Gst.StreamError.FAILED),
    "format": (Gst.stream_error_quark, Gst.StreamError.FORMAT),
    "settings": (Gst.resource_error_quark, Gst.ResourceError.SETTINGS),
    "read": (Gst.resource_error_quark, Gst.ResourceError.READ),
    "write": (Gst.resource_error_quark, Gst.ResourceError.WRITE),
    "not-found": (Gst.resource_error_quark, Gst.ResourceError.NOT_FOUND),
    "negotiation": (Gst.core_error_quark, Gst.CoreError.NEGOTIATION),
}

_gobject = None


def _gobject_lib():
    global _gobject
    if _gobject is None:
        lib = ctypes.CDLL("libgobject-2.0.so.0")
        lib.g_object_ref.argtypes = [ctypes.c_void_p]
        lib.g_object_ref.restype = ctypes.c_void_p
        lib.g_object_force_floating.argtypes = [ctypes.c_void_p]
        _gobject = lib
    return _gobject


def _has_gobject(wrapper) -> bool:
    """True when the instance already exists in C: made by g_object_new (gst_element_factory_make, the
    parser), not by calling the Python class."""
    try:
        return wrapper.__gpointer__ is not None   # ValueError (a NULL pointer) before the GObject exists
    except ValueError:
        return False


def _restore_floating(element) -> None:
    """PyGObject 3.42 sinks the floating reference of a Python-defined element made from C (its instance
    init takes the one reference for the Python wrapper), so gst_element_factory_create finds a
    non-floating element and prints "GStreamer-CRITICAL: The created element should be floating".
    Give the caller the floating reference GStreamer's contract promises: one more reference, marked
    floating (the bin or parser that adds the element sinks it; the wrapper keeps its own)."""
    if element.is_floating():
        return
    ptr = ctypes.pythonapi.PyCapsule_GetPointer
    ptr.restype = ctypes.c_void_p
    ptr.argtypes = [ctypes.py_object, ctypes.c_char_p]
    addr = ptr(element.__gpointer__, None)
    lib = _gobject_lib()
    lib.g_object_ref(addr)
    lib.g_object_force_floating(addr)


def guarded(where, failure):
    """Decorator of a vfunc: an exception becomes an element error (`post_exception`) and the vfunc returns
    `failure`. `where` is a text or a function of the element (e.g. the frame number)."""
    def deco(fn):
        @functools.wraps(fn)
        def vfunc(self, *args):
            try:
                return fn(self, *args)
            except Exception as e:  # noqa: BLE001
                self.post_exception(where(self) if callable(where) else where, e)
                return failure
        return vfunc
    return deco


def starting(fn):
    """Decorator of `do_start`: a new run (errors and warnings reported again), refused property values
    become one settings error, an exception an element error; returns the start's result."""
    @functools.wraps(fn)
    def do_start(self):
        self.reset_errors()
        try:
            errors = self.settings_errors()
            if errors:
                self.post_error("; ".join(errors), kind="settings")
                return False
            return bool(fn(self))
        except Exception as e:  # noqa: BLE001
            self.post_exception("start", e)
            return False
    return do_start


class NrElement(Logging, Properties):
    """Mixin before the GStreamer base class: `class NrX(NrElement, GstBase.BaseTransform)` with
    `PROPERTIES = PropertyTable(...)`, `DEBUG_CATEGORY = debug_category(...)`; errors go through
    `post_error(text, kind=...)` (gst-launch prints `ERROR: from element .../GstNrX:nrx0: <text>`)."""

    def __init__(self):
        made_in_c = _has_gobject(self)
        super().__init__()
        self.nr_props_init()
        self.reset_errors()
        if made_in_c:
            _restore_floating(self)

    def post_error(self, text: str, debug: str | None = None, kind: str = "stream") -> None:
        """Post an element error; the same text is posted once per run (upstream may retry a refused
        caps event several times). `reset_errors()` starts a run."""
        posted = self.__dict__.setdefault("_nr_posted", set())
        if text in posted:
            return
        posted.add(text)
        quark, code = _ERROR_KINDS.get(kind, _ERROR_KINDS["stream"])
        f = sys._getframe(1)
        while f.f_back is not None and f.f_code.co_filename == __file__:
            f = f.f_back
        self.message_full(Gst.MessageType.ERROR, quark(), int(code), text, debug, f.f_code.co_filename,
                          f.f_code.co_name, f.f_lineno)

    def post_exception(self, where: str, exc: BaseException) -> Gst.FlowReturn:
        """Post an element error for an exception raised in a vfunc and return FlowReturn.ERROR. A buffer
        of the wrong size (FrameSizeError) or caps the element cannot take (CapsError) are format errors
        stated as such."""
        if isinstance(exc, (FrameSizeError, CapsError)):
            self.post_error(f"{where}: {exc}", kind="format")
            return Gst.FlowReturn.ERROR
        tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
        self.gst_debug(f"{where}: {type(exc).__name__}: {exc}")
        self.post_error(f"{where}: {type(exc).__name__}: {exc}", tb)
        return Gst.FlowReturn.ERROR

    def reset_errors(self) -> None:
        self.__dict__["_nr_posted"] = set()
        self.__dict__["_nr_warned"] = {}
        rearm_warnings()          # a new run reports Python warnings again

    def sync_controlled(self, buf) -> None:
        """Apply GstController curves of CONTROLLABLE properties at the buffer's stream time (BaseTransform
        leaves this to subclasses)."""
        ts = buf.pts
        if ts == Gst.CLOCK_TIME_NONE:
            return
        st = self.segment.to_stream_time(Gst.Format.TIME, ts)
        if st != Gst.CLOCK_TIME_NONE:
            self.sync_values(st)

    def nr_before_transform(self, buf):
        """`do_before_transform = NrElement.nr_before_transform` for elements with controllable properties."""
        try:
            self.sync_controlled(buf)
        except Exception as e:  # noqa: BLE001
            self.gst_warn(f"controller sync failed: {e}")
