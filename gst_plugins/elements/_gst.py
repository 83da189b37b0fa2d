"""GStreamer and numpy imports of the elements, and GStreamer initialisation (idempotent).

Every name is bound before `Gst.init`: with GST_REGISTRY_FORK=no (an app in a venv) the registry scan runs
inside `Gst.init`, in this process, and the plugin loader then imports the element shims, which import
this module again while it is still initialising.
"""
from __future__ import annotations

import gi

gi.require_version("Gst", "1.0")
gi.require_version("GstBase", "1.0")
gi.require_version("GstVideo", "1.0")
from gi.repository import GLib, GObject, Gst, GstBase, GstVideo  # noqa: E402

import numpy as np  # noqa: E402

__all__ = ["GLib", "GObject", "Gst", "GstBase", "GstVideo", "np"]

if not Gst.is_initialized():
    Gst.init(None)
