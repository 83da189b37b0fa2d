"""GStreamer debug logging of the elements in their own debug categories (`GST_DEBUG=nrreconstruct:6`
works as for C elements), and Python warnings raised inside an element as bus WARNING messages."""
from __future__ import annotations

import contextlib
import ctypes
import sys
import threading
import warnings

from ._gst import Gst

# PyGObject 3.42 / gst-python 1.22 expose Gst.debug_log_literal (takes a Gst.DebugCategory) but no way to
# create a category (Gst.DebugCategory has no constructor, GST_DEBUG_CATEGORY_INIT is a C macro); the
# gst-python helpers Gst.debug()/Gst.log() all log to the single category "python". So the category is
# created with `_gst_debug_category_new` (the public ABI symbol behind GST_DEBUG_CATEGORY_INIT) through
# ctypes and then looked up as a Gst.DebugCategory. Without libgstreamer reachable by ctypes, lines go to
# the "python" category.

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


# warnings.catch_warnings() is process-global, not per thread (elements run in several streaming threads),
# so a hook on warnings._showwarnmsg (which catch_warnings, pytest's included, does not replace) looks up the
# element running in the current thread and posts the warning on the bus; outside an element the usual
# display happens unchanged. The warning filters are left alone: their "default" action shows a warning once
# per location, and each element start (`rearm_warnings`) invalidates that memory, so every run reports it.

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


def rearm_warnings() -> None:
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


class Logging:
    """Mixin: debug logging in the element's category (class attribute DEBUG_CATEGORY, made with
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
