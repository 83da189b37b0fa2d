"""GStreamer elements of nrhdr (docs/ELEMENTS.md).

Apps register every element in-process with one call::

    import gst_plugins
    gst_plugins.register_all()          # Gst.init if needed, then nrvalidity, nrcrosstalk, ...
    pipeline = Gst.parse_launch("filesrc ... ! nrvalidity profile=camera.json ! ...")

For gst-launch-1.0 / gst-inspect-1.0 use `nrhdr launch` / `nrhdr inspect` (gst_plugins.runtime), which set
GST_PLUGIN_PATH and PYTHONPATH for the Python plugin loader. Importing this package is cheap: GStreamer and
the element modules are imported only by `register_all()`.
"""
from __future__ import annotations

import threading

FACTORIES = ("nrvalidity", "nrcrosstalk", "nrreconstruct", "nrtonemap", "nrexrsink", "nrcamsrc", "nrimagesrc", "nrhdrenc")

_lock = threading.Lock()
_registered = False


def _init_gstreamer_first() -> None:
    """Gst.init before any element module is imported: with GST_REGISTRY_FORK=no the registry scan runs in
    Gst.init, in this process, and the plugin loader imports the element shims; a half-imported element
    module there would cache the python plugin with no elements in the registry."""
    import gi
    gi.require_version("Gst", "1.0")
    from gi.repository import Gst
    if not Gst.is_initialized():
        Gst.init(None)


def register_all() -> list[str]:
    """Register all nrhdr elements with GStreamer in this process (idempotent, thread-safe). Initialises
    GStreamer if needed. Returns the factory names. The element classes are the same objects the plugin
    loader uses, so registering in a process that also loaded the plugin does not clash."""
    global _registered
    with _lock:
        _init_gstreamer_first()
        from .elements import ELEMENTS, element_class
        from .elements._gst import Gst
        if _registered:
            return list(ELEMENTS)
        for name in ELEMENTS:
            cls = element_class(name)
            f = Gst.ElementFactory.find(name)
            if f is not None and f.get_element_type() == cls.__gtype__:
                continue
            if not Gst.Element.register(None, name, Gst.Rank.NONE, cls):
                raise RuntimeError(f"could not register GStreamer element {name}")
        _registered = True
        return list(ELEMENTS)
