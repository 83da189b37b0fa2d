"""nrtonemap: HDR frames to display video. transfer=log (default): logarithmic tone mapping (paper section 5)
to GRAY8 or GRAY16_LE for any stock sink (format negotiated with downstream). transfer=pq / hlg (beyond the
paper): 10-bit BT.2100 PQ (SMPTE ST 2084) or HLG (ARIB STD-B67) codes, narrow range, in GRAY16_LE/BE words
(code << 6) with colorimetry=bt2100-pq / bt2100-hlg in the caps, for HDR monitors and 10-bit encoders
(`videoconvert ! video/x-raw,format=I420_10LE ! vp9enc`).

The normaliser is fixed (the caps' `white` / `diffuse-white`, set by nrvalidity from the profile, or the
`white` property) or smoothed over time (`nrhdr_core.tonemap.WhiteTracker`), never a per-frame min/max, so
video does not flicker. pixel-aspect-ratio and interlace-mode pass through.
"""
from __future__ import annotations

import dataclasses
import math
import time

from ._common import LiveTiming, live_latency_property  # live operation: QoS, latency (issue #7)
from ._common import (CONTROLLABLE, HDR_MEDIA_TYPE, MUTABLE_PLAYING, MUTABLE_READY, Choice, ErrorPoster,
                      GObject, Gst, GstBase, GstVideo, HdrInfo, copy_fields, debug_category, hdr_template_caps,
                      map_hdr, map_video, np, transform_caps_by_structure)

NORMALISE = ("caps", "fixed", "smoothed")
TRANSFERS = ("log", "pq", "hlg")
COLORIMETRY = {"pq": "bt2100-pq", "hlg": "bt2100-hlg"}
LOG_FORMATS = ("GRAY8", "GRAY16_LE")
HDR_FORMATS = ("GRAY16_LE", "GRAY16_BE")   # BE: pngenc writes 16-bit PNG from it directly
DEFAULT_CONTRAST = 1000.0  # = nrhdr_core.tonemap.DEFAULT_CONTRAST (not imported here: keeps import light)
DEFAULT_REFERENCE_WHITE = 203.0  # = nrhdr_core.tonemap.REFERENCE_WHITE_NITS (ITU-R BT.2408)
_INT = "(int)[1,2147483647]"
_FPS = "(fraction)[0/1,2147483647/1]"


def _src_template() -> Gst.Caps:
    return Gst.Caps.from_string(
        f"video/x-raw, format=(string){{ GRAY8, GRAY16_LE }}, width={_INT}, height={_INT}, framerate={_FPS}; "
        f"video/x-raw, format=(string){{ GRAY16_LE, GRAY16_BE }}, width={_INT}, height={_INT}, "
        f"framerate={_FPS}, colorimetry=(string){{ bt2100-pq, bt2100-hlg }}")


@dataclasses.dataclass(frozen=True)
class ToneParams:
    normalise: str = "caps"
    white: float = 0.0
    exposure: float = 0.0
    contrast: float = DEFAULT_CONTRAST
    smoothing: float = 0.1
    reference_white: float = DEFAULT_REFERENCE_WHITE


class NrTonemap(ErrorPoster, LiveTiming, GstBase.BaseTransform):
    __gtype_name__ = "GstNrTonemap"
    DEBUG_CATEGORY = debug_category("nrtonemap", "nrhdr tone mapping and HDR (PQ/HLG) output")
    __gstmetadata__ = (
        "nrhdr tone mapping and HDR output",
        "Filter/Converter/Video",
        "Linear HDR frames (other/x-nrhdr) to display video: logarithmic tone mapping (paper section 5) to "
        "GRAY8/GRAY16_LE normalised by a fixed or temporally smoothed white (no flicker), or 10-bit BT.2100 "
        "PQ / HLG (transfer=pq|hlg) with bt2100 colorimetry",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, hdr_template_caps()),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, _src_template()),
    )

    do_gst_base_transform_query = LiveTiming.nr_live_query
    processing_latency = live_latency_property()

    def __init__(self):
        super().__init__()
        self.nr_live_init()
        self._params = ToneParams()
        self._normalise = Choice("normalise", NORMALISE, "caps")
        self._transfer = Choice("transfer", TRANSFERS, "log")
        self._out_transfer = "log"
        self._byteswap = False
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

    @GObject.Property(type=str, default="log", nick="Transfer function",
                      blurb="Output: 'log' = the paper's logarithmic tone mapping to SDR GRAY8/GRAY16_LE; "
                            "'pq' = SMPTE ST 2084, 'hlg' = ARIB STD-B67: 10-bit BT.2100 narrow-range codes "
                            "(64..940) << 6 in GRAY16_LE/BE, colorimetry bt2100-pq / bt2100-hlg "
                            "(one of: log, pq, hlg)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_READY)
    def transfer(self):
        return self._transfer.value

    @transfer.setter
    def transfer(self, value):
        self.set_choice(self._transfer, value)

    @GObject.Property(type=float, default=DEFAULT_REFERENCE_WHITE, minimum=1.0, maximum=10000.0,
                      nick="Reference white (cd/m2)",
                      blurb="transfer=pq/hlg: display luminance of the scene's diffuse white (the caps' "
                            "diffuse-white = the regular pixels' white; with normalise=fixed/smoothed the "
                            "white); brighter values keep their ratio (ITU-R BT.2408: 203)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING | CONTROLLABLE)
    def reference_white(self):
        return self._params.reference_white

    @reference_white.setter
    def reference_white(self, value):
        self._update(reference_white=float(value))

    @GObject.Property(type=float, default=0.0, minimum=0.0, maximum=1e12, nick="White",
                      blurb="Linear value mapped to full scale (log) or to reference-white (pq/hlg) with "
                            "normalise=fixed; 0 = the caps' white",
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
            for c in (self._normalise, self._transfer):
                if c.invalid:
                    self.post_error(c.invalid, kind="settings")
                    return False
            from nrhdr_core import tonemap
            if self._transfer.value == "log":
                self.nr_warmup(tonemap.warmup)
            else:
                self.nr_warmup(tonemap.warmup_hdr)
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
        transfer = self._transfer.value

        def to_raw(s):
            out = []
            for fmt in (LOG_FORMATS if transfer == "log" else HDR_FORMATS):
                n = Gst.Structure.new_empty("video/x-raw")
                n.set_value("format", fmt)
                copy_fields(s, n)
                if transfer != "log":
                    n.set_value("colorimetry", COLORIMETRY[transfer])
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

    def do_decide_allocation(self, query):
        """Output frames from a buffer pool: downstream's if it proposes one (videoconvert, video sinks),
        else a plain pool of this size that BaseTransform creates (pngenc, appsink propose none), so
        frames are allocated once, not per frame."""
        try:
            if query.get_n_allocation_pools() == 0:
                caps, _need_pool = query.parse_allocation()
                vi = GstVideo.VideoInfo.new_from_caps(caps) if caps is not None else None
                if vi is not None:
                    query.add_allocation_pool(None, vi.size, 2, 0)
                    self.gst_debug(f"downstream proposed no pool: own pool of {vi.size}-byte frames")
        except Exception as e:  # noqa: BLE001 - fall back to BaseTransform's per-frame allocation
            self.gst_debug(f"decide_allocation: {e}")
        return GstBase.BaseTransform.do_decide_allocation(self, query)

    def do_set_caps(self, incaps, outcaps):
        try:
            self._in_info = HdrInfo.from_caps(incaps)
            vi = GstVideo.VideoInfo.new_from_caps(outcaps)
            if vi is None:
                self.post_error(f"cannot parse output caps {outcaps.to_string()}", kind="format")
                return False
            fmt = vi.finfo.format
            transfer = self._transfer.value
            formats = LOG_FORMATS if transfer == "log" else HDR_FORMATS
            if vi.finfo.name not in formats:
                self.post_error(f"output format {vi.finfo.name} does not fit transfer={transfer} (needs "
                                f"{' or '.join(formats)})", kind="format")
                return False
            self._out_dtype = np.uint8 if fmt == GstVideo.VideoFormat.GRAY8 else np.dtype("<u2")
            self._byteswap = fmt == GstVideo.VideoFormat.GRAY16_BE
            self._out_transfer = transfer
            self._out_info = vi
            self._tracker = None
            self.gst_debug(f"caps: {incaps.to_string()} -> {outcaps.to_string()} (transfer={transfer})")
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("set_caps", e)
            return False

    # ---- data ---------------------------------------------------------------------------------------
    def _white(self, p: ToneParams, values, hdr: bool = False) -> float:
        """The normaliser: full scale of the log curve, or (hdr) the value shown at reference white."""
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
        if hdr and p.normalise == "caps" and self._in_info.diffuse_white is not None:
            return self._in_info.diffuse_white
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
            self.gst_warn(f"controller sync failed: {e}")

    def do_transform(self, inbuf, outbuf):
        p = self._params
        try:
            if self._in_info is None or self._out_info is None:
                self.post_error("no caps negotiated before the first buffer", kind="negotiation")
                return Gst.FlowReturn.NOT_NEGOTIATED
            from nrhdr_core import tonemap
            transfer = self._out_transfer
            t0 = time.perf_counter()
            with self.warnings_to_bus(), map_hdr(inbuf, self._in_info, write=False) as (values, _state), \
                    map_video(outbuf, self._out_info, self._out_dtype, write=True) as out:
                white = self._white(p, values, hdr=transfer != "log")
                if not (math.isfinite(white) and white > 0):
                    raise ValueError(f"tone mapping white is {white}")
                # kernels write straight into the mapped output (strided rows are fine for numba)
                if transfer == "log":
                    tonemap.log_tonemap(values, white, exposure_stops=p.exposure, contrast=p.contrast, out=out)
                else:
                    tonemap.hdr_encode(values, white, transfer, reference_white=p.reference_white,
                                       exposure_stops=p.exposure, out=out)
                    if self._byteswap:
                        out.byteswap(inplace=True)
            if self.gst_debug_enabled(Gst.DebugLevel.LOG):
                self.gst_log(f"frame {self._frames} pts {Gst.TIME_ARGS(inbuf.pts)}: {transfer} "
                             f"white={white:.6g} exposure={p.exposure:+.2f} in "
                             f"{(time.perf_counter() - t0) * 1e3:.2f} ms")
            self._frames += 1
            return Gst.FlowReturn.OK
        except Exception as e:  # noqa: BLE001
            return self.post_exception(f"frame {self._frames}", e)
