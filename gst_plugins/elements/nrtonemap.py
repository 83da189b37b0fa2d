"""nrtonemap: logarithmic tone mapping of HDR frames (paper section 5) to GRAY8 or GRAY16_LE for any stock
sink (format negotiated with downstream). The normaliser is fixed (the caps' `white`, set by nrvalidity
from the profile, or the `white` property) or smoothed over time (`nrhdr_core.tonemap.WhiteTracker`),
never a per-frame min/max, so video does not flicker.
"""
from __future__ import annotations

import dataclasses
import math

from ._common import LiveTiming, live_latency_property  # live operation: QoS, latency (issue #7)
from ._common import (CONTROLLABLE, HDR_MEDIA_TYPE, MUTABLE_PLAYING, Choice, ErrorPoster, GObject, Gst,
                      GstBase, GstVideo, HdrInfo, copy_fields, hdr_template_caps, map_hdr, map_video, np,
                      raw_template_caps, transform_caps_by_structure)

NORMALISE = ("caps", "fixed", "smoothed")
DEFAULT_CONTRAST = 1000.0  # = nrhdr_core.tonemap.DEFAULT_CONTRAST (not imported here: keeps import light)


@dataclasses.dataclass(frozen=True)
class ToneParams:
    normalise: str = "caps"
    white: float = 0.0
    exposure: float = 0.0
    contrast: float = DEFAULT_CONTRAST
    smoothing: float = 0.1


class NrTonemap(ErrorPoster, LiveTiming, GstBase.BaseTransform):
    __gtype_name__ = "GstNrTonemap"
    __gstmetadata__ = (
        "nrhdr logarithmic tone mapping",
        "Filter/Converter/Video",
        "Logarithmic tone mapping (paper section 5) of linear HDR frames (other/x-nrhdr) to GRAY8 or "
        "GRAY16_LE video, normalised by a fixed or temporally smoothed white (no flicker)",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, hdr_template_caps()),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS,
                            raw_template_caps("{ GRAY8, GRAY16_LE }")),
    )

    do_gst_base_transform_query = LiveTiming.nr_live_query
    processing_latency = live_latency_property()

    def __init__(self):
        super().__init__()
        self.nr_live_init()
        self._params = ToneParams()
        self._normalise = Choice("normalise", NORMALISE, "caps")
        self._in_info = None
        self._out_info = None
        self._out_dtype = np.uint8
        self._tracker = None
        self._tracker_speed = None
        self._frames = 0
        self.set_in_place(False)
        self.set_passthrough(False)

    def _update(self, **kw):
        self._params = dataclasses.replace(self._params, **kw)

    # ---- properties ---------------------------------------------------------------------------------
    @GObject.Property(type=str, default="caps", nick="Normaliser",
                      blurb="Where the white (value mapped to full scale) comes from: 'caps' = the caps field "
                            "white (4094 x ND, set by nrvalidity from the profile); 'fixed' = the white "
                            "property; 'smoothed' = a high percentile of each frame smoothed over time "
                            "(smoothing) (one of: caps, fixed, smoothed)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING)
    def normalise(self):
        return self._params.normalise

    @normalise.setter
    def normalise(self, value):
        v = self.set_choice(self._normalise, value)
        if v is not None:
            self._update(normalise=v)

    @GObject.Property(type=float, default=0.0, minimum=0.0, maximum=1e12, nick="White",
                      blurb="Linear value mapped to full scale with normalise=fixed; 0 = the caps' white",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING | CONTROLLABLE)
    def white(self):
        return self._params.white

    @white.setter
    def white(self, value):
        self._update(white=float(value))

    @GObject.Property(type=float, default=0.0, minimum=-20.0, maximum=20.0, nick="Exposure",
                      blurb="Exposure correction in stops (x 2^exposure before tone mapping)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING | CONTROLLABLE)
    def exposure(self):
        return self._params.exposure

    @exposure.setter
    def exposure(self, value):
        self._update(exposure=float(value))

    @GObject.Property(type=float, default=DEFAULT_CONTRAST, minimum=1e-3, maximum=1e9, nick="Contrast",
                      blurb="Contrast q of the logarithmic curve y = log(1 + q x) / log(1 + q): larger = "
                            "more shadow detail",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING | CONTROLLABLE)
    def contrast(self):
        return self._params.contrast

    @contrast.setter
    def contrast(self, value):
        self._update(contrast=float(value))

    @GObject.Property(type=float, default=0.1, minimum=0.001, maximum=1.0, nick="Smoothing speed",
                      blurb="normalise=smoothed: weight of the current frame in the running white, "
                            "white = speed * frame + (1 - speed) * previous (1 = no smoothing)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING | CONTROLLABLE)
    def smoothing(self):
        return self._params.smoothing

    @smoothing.setter
    def smoothing(self, value):
        self._update(smoothing=float(value))

    # ---- state --------------------------------------------------------------------------------------
    def do_start(self):
        self.reset_errors()
        try:
            if self._normalise.invalid:
                self.post_error(self._normalise.invalid, kind="settings")
                return False
            from nrhdr_core import tonemap
            if hasattr(tonemap, "warmup"):
                self.nr_warmup(tonemap.warmup)
            self._tracker = None
            self._frames = 0
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("start", e)
            return False

    def do_stop(self):
        self._in_info = self._out_info = None
        self._tracker = None
        return True

    def do_sink_event(self, event):
        if event.type == Gst.EventType.FLUSH_STOP:
            self._tracker = None  # a seek restarts the temporal smoothing
        return GstBase.BaseTransform.do_sink_event(self, event)

    # ---- caps ---------------------------------------------------------------------------------------
    def do_transform_caps(self, direction, caps, filt):
        def to_raw(s):
            out = []
            for fmt in ("GRAY8", "GRAY16_LE"):
                n = Gst.Structure.new_empty("video/x-raw")
                n.set_value("format", fmt)
                copy_fields(s, n)
                out.append(n)
            return out

        def to_hdr(s):
            n = Gst.Structure.new_empty(HDR_MEDIA_TYPE)
            copy_fields(s, n)
            return [n]

        return transform_caps_by_structure(caps, filt, to_raw if direction == Gst.PadDirection.SINK
                                           else to_hdr, self)

    def do_transform_size(self, direction, caps, size, othercaps):
        try:
            if direction == Gst.PadDirection.SINK:
                vi = GstVideo.VideoInfo.new_from_caps(othercaps)
                return (vi is not None), (vi.size if vi is not None else 0)
            info = HdrInfo.from_caps(othercaps)
            return True, info.size
        except Exception:  # noqa: BLE001
            return False, 0

    def do_set_caps(self, incaps, outcaps):
        try:
            self._in_info = HdrInfo.from_caps(incaps)
            vi = GstVideo.VideoInfo.new_from_caps(outcaps)
            if vi is None:
                self.post_error(f"cannot parse output caps {outcaps.to_string()}", kind="format")
                return False
            fmt = vi.finfo.format
            if fmt == GstVideo.VideoFormat.GRAY8:
                self._out_dtype = np.uint8
            elif fmt == GstVideo.VideoFormat.GRAY16_LE:
                self._out_dtype = np.dtype("<u2")
            else:
                self.post_error(f"unsupported output format {vi.finfo.name}", kind="format")
                return False
            self._out_info = vi
            self._tracker = None
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("set_caps", e)
            return False

    # ---- data ---------------------------------------------------------------------------------------
    def _white(self, p: ToneParams, values) -> float:
        from nrhdr_core import tonemap
        if p.normalise == "smoothed":
            if self._tracker is None or self._tracker_speed != p.smoothing:
                old = self._tracker.white if self._tracker is not None else None
                self._tracker = tonemap.WhiteTracker(p.smoothing)
                self._tracker.white = old
                self._tracker_speed = p.smoothing
            return float(self._tracker.update(values))
        if p.normalise == "fixed" and p.white > 0:
            return p.white
        w = self._in_info.white
        if w is None:
            if p.normalise == "fixed":
                raise ValueError("normalise=fixed needs white > 0 or a 'white' field in the caps")
            raise ValueError("the input caps have no 'white' field (put nrvalidity upstream, or use "
                             "normalise=fixed white=... or normalise=smoothed)")
        return w

    def do_before_transform(self, buf):
        try:
            self.sync_controlled(buf)
        except Exception as e:  # noqa: BLE001
            Gst.warning(f"{self.get_name()}: controller sync failed: {e}")

    def do_transform(self, inbuf, outbuf):
        p = self._params
        try:
            if self._in_info is None or self._out_info is None:
                self.post_error("no caps negotiated before the first buffer", kind="negotiation")
                return Gst.FlowReturn.NOT_NEGOTIATED
            from nrhdr_core import tonemap
            with map_hdr(inbuf, self._in_info, write=False) as (values, _state), \
                    map_video(outbuf, self._out_info, self._out_dtype, write=True) as out:
                white = self._white(p, values)
                if not (math.isfinite(white) and white > 0):
                    raise ValueError(f"tone mapping white is {white}")
                if out.flags.c_contiguous:
                    tonemap.log_tonemap(values, white, exposure_stops=p.exposure, contrast=p.contrast, out=out)
                else:
                    tmp = np.empty(out.shape, out.dtype)
                    tonemap.log_tonemap(values, white, exposure_stops=p.exposure, contrast=p.contrast, out=tmp)
                    out[...] = tmp
            self._frames += 1
            return Gst.FlowReturn.OK
        except Exception as e:  # noqa: BLE001
            return self.post_exception(f"frame {self._frames}", e)
