"""The names apps, tests and benchmarks use from the elements' shared modules (one import line): HDR frame
caps and mapping, buffer pool, profile loading, GStreamer modules. Each name is defined in the module of
its concern: `_caps`, `_buffers`, `_log`, `_props`, `_profiles`, `_live`, `_base`."""
from __future__ import annotations

from ._base import NrElement, guarded, starting
from ._buffers import (FrameSizeError, HdrPool, alloc_hdr_buffer, check_hdr_buffer, check_video_buffer,
                       copy_timestamps, gray16_buffer, map_hdr, map_sample, map_video)
from ._caps import (BAYER_FORMATS, BAYER_MEDIA_TYPE, HDR_LAYOUT, HDR_MEDIA_TYPE, LAYOUTS, RGB_LAYOUT, CapsError,
                    HdrInfo, bayer_template_caps, copy_fields, hdr_template_caps, hdr_transform_templates,
                    raw_template_caps, source_caps, transform_caps_by_structure)
from ._gst import GLib, GObject, Gst, GstBase, GstVideo, np
from ._live import LATENCY_PROP, LiveTiming
from ._log import debug_category
from ._profiles import ALLOW_OUTSIDE_PROP, load_profile
from ._props import CONTROLLABLE, MUTABLE_PLAYING, MUTABLE_READY, Prop, PropertyTable

__all__ = ["ALLOW_OUTSIDE_PROP", "BAYER_FORMATS", "BAYER_MEDIA_TYPE", "CONTROLLABLE", "CapsError", "FrameSizeError",
           "GLib", "GObject", "Gst", "GstBase", "GstVideo", "HDR_LAYOUT", "HDR_MEDIA_TYPE", "HdrInfo", "HdrPool",
           "LATENCY_PROP", "LAYOUTS", "LiveTiming", "MUTABLE_PLAYING", "MUTABLE_READY", "NrElement", "Prop",
           "PropertyTable", "RGB_LAYOUT", "alloc_hdr_buffer", "bayer_template_caps", "check_hdr_buffer",
           "check_video_buffer", "copy_fields", "copy_timestamps", "debug_category", "gray16_buffer", "guarded",
           "hdr_template_caps", "hdr_transform_templates", "load_profile", "map_hdr", "map_sample", "map_video", "np",
           "raw_template_caps", "source_caps", "starting", "transform_caps_by_structure"]
