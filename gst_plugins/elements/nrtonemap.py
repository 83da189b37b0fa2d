"""nrtonemap: HDR frames to display video. transfer=log (default): SDR tone mapping to GRAY8 or GRAY16_LE for any
stock sink (format negotiated with downstream), by the paper's logarithmic curve (operator=log, section 5) or
the local base/detail operator (operator=local, docs/TONEMAP.md). transfer=pq / hlg (beyond the
paper): 10-bit BT.2100 PQ (SMPTE ST 2084) or HLG (ARIB STD-B67) codes, narrow range, in GRAY16_LE/BE words
(code << 6) with colorimetry=bt2100-pq / bt2100-hlg in the caps, for HDR monitors and 10-bit encoders
(`nrhdrenc`, or `videoconvert ! video/x-raw,format=I420_10LE ! x265enc`); `peak` rolls highlights off to the
mastering display's peak (ITU-R BT.2390 EETF).

Colour frames (layout rgb-f32-u8-planar, docs/COLOUR.md "Colour output"): white balance (`white-balance`),
then transfer=log: the luminance tone mapped, hue and saturation kept (`nrhdr_core.tonemap.tonemap_rgb`), to
8-bit sRGB `RGB`; transfer=pq / hlg: BT.709 camera RGB converted to BT.2020 primaries, PQ / HLG per channel
(`tonemap.hdr_encode_rgb`) and BT.2020 non-constant-luminance Y'CbCr, 10-bit narrow range, in I420_10LE or
Y444_10LE (`hdr_output.ycbcr_frame`).

The normaliser is fixed (the caps' `white` / `diffuse-white`, set by nrvalidity from the profile, or the
`white` property) or smoothed over time (`nrhdr_core.tonemap.WhiteTracker`, or `AutoWhite` where the caps
carry no white), never a per-frame min/max, so video does not flicker. pixel-aspect-ratio and interlace-mode
pass through.
"""
from __future__ import annotations

import math
import time

from nrhdr_core.tonemap import DEFAULT_CONTRAST, REFERENCE_WHITE_NITS, SDR_OPERATORS
from nrhdr_core.tonemap import TRANSFERS as HDR_TRANSFERS

from ._common import (HDR_LAYOUT, HDR_MEDIA_TYPE, LATENCY_PROP, LAYOUTS, RGB_LAYOUT, Gst, GstBase, GstVideo,
                      HdrInfo, LiveTiming, NrElement, Prop, PropertyTable, copy_fields, debug_category, guarded,
                      hdr_template_caps, load_profile, map_hdr, map_video, np, raw_template_caps, starting,
                      transform_caps_by_structure)
from ._buffers import RW

NORMALISE = ("caps", "fixed", "smoothed", "auto")
DEFAULT_OPERATOR = "local"     # docs/TONEMAP.md: the measured choice
TRANSFERS = ("log",) + HDR_TRANSFERS
COLORIMETRY = {"pq": "bt2100-pq", "hlg": "bt2100-hlg"}
LOG_FORMATS = ("GRAY8", "GRAY16_LE")
HDR_FORMATS = ("GRAY16_LE", "GRAY16_BE")   # BE: pngenc writes 16-bit PNG from it directly
RGB_LOG_FORMATS = ("RGB",)                  # colour frames: 8-bit sRGB
RGB_HDR_FORMATS = ("I420_10LE", "Y444_10LE")  # colour frames: BT.2020 NCL Y'CbCr (x265enc's Main 10: I420_10LE)
WHITE_BALANCE = ("profile", "grey-world", "none")
# output formats per (colour input, transfer is log)
_FORMATS = {(False, True): LOG_FORMATS, (False, False): HDR_FORMATS, (True, True): RGB_LOG_FORMATS,
            (True, False): RGB_HDR_FORMATS}


def _src_template() -> Gst.Caps:
    caps = raw_template_caps("{ GRAY8, GRAY16_LE, RGB }")
    caps.append(raw_template_caps("{ GRAY16_LE, GRAY16_BE, I420_10LE, Y444_10LE }",
                                  "colorimetry=(string){ bt2100-pq, bt2100-hlg }"))
    return caps


def _field_values(s: Gst.Structure, field: str) -> tuple | None:
    """The fixed string of a caps field, or every string of its list; None when absent or of another type."""
    if not s.has_field(field):
        return None
    one = s.get_string(field)
    if one is not None:
        return (one,)
    try:
        v = s.get_value(field)
        return tuple(str(x) for x in v)
    except Exception:  # noqa: BLE001 - a range or another type: any value
        return None


def _colour_kinds(s: Gst.Structure) -> tuple:
    """Which inputs (False: one plane, True: colour) an other/x-nrhdr structure can be."""
    layouts = _field_values(s, "layout")
    if layouts is None:
        return (False,) if not s.has_field("layout") else (False, True)
    return tuple(dict.fromkeys(lay == RGB_LAYOUT for lay in layouts if lay in LAYOUTS)) or (False,)


def _mapped_planes(buf: Gst.Buffer, vi: GstVideo.VideoInfo):
    """(offsets, strides) of the planes of an output video buffer: its GstVideoMeta when it has one, else the
    caps' VideoInfo."""
    try:
        meta = GstVideo.buffer_get_video_meta(buf)
    except Exception:  # noqa: BLE001 - no usable meta: the caps' layout
        meta = None
    n = vi.finfo.n_planes
    if meta is not None:
        return [int(meta.offset[k]) for k in range(n)], [int(meta.stride[k]) for k in range(n)]
    return [int(vi.offset[k]) for k in range(n)], [int(vi.stride[k]) for k in range(n)]


PROPERTIES = PropertyTable("GstNrTonemap", [
    Prop("normalise", NORMALISE, "caps", "Normaliser",
         "Where the white (value mapped to full scale) comes from: 'caps' = the caps field white (4094 x ND, "
         "set by nrvalidity from the profile; transfer=log without it: as 'auto'); 'fixed' = the white "
         "property; 'smoothed' = a high percentile of each frame smoothed over time (smoothing); 'auto' "
         "(transfer=log) = the frame's log-average shown at the natural mean level, smoothed over time",
         playing=True),
    Prop("operator", SDR_OPERATORS, DEFAULT_OPERATOR, "SDR operator",
         "transfer=log: 'log' = the paper's global curve y = log(1 + q x) / log(1 + q); 'local' = base/detail "
         "split on log luminance with a guided filter, base range compressed, detail and brightness set "
         "from statistics smoothed over time (smoothing); colour frames: the luminance is tone mapped and "
         "each channel keeps its ratio to it (hue and saturation kept)", playing=True),
    Prop("transfer", TRANSFERS, "log", "Transfer function",
         "Output: 'log' = the paper's logarithmic tone mapping to SDR GRAY8/GRAY16_LE; 'pq' = SMPTE ST 2084, "
         "'hlg' = ARIB STD-B67: 10-bit BT.2100 narrow-range codes (64..940) << 6 in GRAY16_LE/BE, "
         "colorimetry bt2100-pq / bt2100-hlg; colour frames: RGB (log), BT.2020 Y'CbCr I420_10LE / "
         "Y444_10LE (pq/hlg, BT.709 camera RGB converted to BT.2020 primaries)"),
    Prop("white-balance", WHITE_BALANCE, "profile", "White balance",
         "Colour frames: 'profile' = the gains of the profile named in the caps (white_balance; none when "
         "the caps name no profile); 'grey-world' = gains that make the frame's mean colour grey, ignoring "
         "clipped and near-black pixels, smoothed over time (smoothing); 'none' = camera RGB as it is",
         playing=True),
    Prop("saturation", float, 1.0, "Saturation",
         "Colour frames, transfer=log: exponent s of each channel's ratio to the luminance, (c / L)^s (1 = "
         "the scene's saturation; below 1 less)", minimum=0.01, maximum=4.0, playing=True, controllable=True),
    Prop("reference-white", float, REFERENCE_WHITE_NITS, "Reference white (cd/m2)",
         "transfer=pq/hlg: display luminance of the scene's diffuse white (the caps' diffuse-white = the "
         "regular pixels' white; with normalise=fixed/smoothed the white); brighter values keep their ratio "
         "(ITU-R BT.2408: 203)", minimum=1.0, maximum=10000.0, playing=True, controllable=True),
    Prop("peak", float, 0.0, "Peak (cd/m2)",
         "transfer=pq/hlg: the mastering display's peak: display light above it is rolled off by the ITU-R "
         "BT.2390 EETF from the caps' white (the brightest the sensor gives) down to it, instead of clipped; "
         "0 = no roll-off (PQ clips at 10000, HLG at E = 1)", minimum=0.0, maximum=10000.0, playing=True,
         controllable=True),
    Prop("white", float, 0.0, "White",
         "Linear value mapped to full scale (log) or to reference-white (pq/hlg) with normalise=fixed; 0 = "
         "the caps' white", minimum=0.0, maximum=1e12, playing=True, controllable=True),
    Prop("exposure", float, 0.0, "Exposure", "Exposure correction in stops (x 2^exposure before tone mapping)",
         minimum=-20.0, maximum=20.0, playing=True, controllable=True),
    Prop("contrast", float, DEFAULT_CONTRAST, "Contrast",
         "Contrast q of the logarithmic curve y = log(1 + q x) / log(1 + q): larger = more shadow detail",
         minimum=1e-3, maximum=1e9, playing=True, controllable=True),
    Prop("smoothing", float, 0.1, "Smoothing speed",
         "normalise=smoothed/auto and operator=local: weight of the current frame in the running white "
         "and statistics, value = speed * frame + (1 - speed) * previous (1 = no smoothing)", minimum=0.001,
         maximum=1.0, playing=True, controllable=True),
    LATENCY_PROP,
])


class NrTonemap(NrElement, LiveTiming, GstBase.BaseTransform):
    __gtype_name__ = "GstNrTonemap"
    PROPERTIES = PROPERTIES
    DEBUG_CATEGORY = debug_category("nrtonemap", "nrhdr tone mapping and HDR (PQ/HLG) output")
    __gstmetadata__ = (
        "nrhdr tone mapping and HDR output",
        "Filter/Converter/Video",
        "Linear HDR frames (other/x-nrhdr) to display video: SDR tone mapping (a local operator, or the "
        "paper's logarithmic curve, section 5) to GRAY8/GRAY16_LE normalised by a fixed or temporally "
        "smoothed white (no flicker), or 10-bit BT.2100 "
        "PQ / HLG (transfer=pq|hlg) with bt2100 colorimetry; colour frames to RGB or BT.2020 Y'CbCr, hue kept",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS,
                            hdr_template_caps(layouts=LAYOUTS)),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, _src_template()),
    )

    do_gst_base_transform_query = LiveTiming.nr_live_query
    do_before_transform = NrElement.nr_before_transform

    def __init__(self):
        super().__init__()
        self.nr_live_init()
        self._out_transfer = "log"
        self._byteswap = False
        self._in_info = None
        self._out_info = None
        self._out_dtype = np.uint8
        self._tracker = None
        self._tracker_speed = None
        self._profile_gains = None
        self._sdr_reset()
        self._frames = 0
        self.set_in_place(False)
        self.set_passthrough(False)

    # ---- state --------------------------------------------------------------------------------------
    @starting
    def do_start(self):
        from nrhdr_core import chain
        self.nr_warmup(chain.warmup, stages=("tonemap",), transfers=(self.settings.transfer,), elements=True)
        if self.settings.transfer == "log" and self.settings.operator == "local":
            from nrhdr_core import tonemap
            self.nr_warmup(tonemap.warmup_local, elements=True)
        self._tracker = None
        self._sdr_reset()
        self._frames = 0
        return True

    def do_stop(self):
        self._in_info = self._out_info = None
        self._tracker = None
        self._sdr_reset()
        return True

    def do_sink_event(self, event):
        if event.type == Gst.EventType.FLUSH_STOP:
            self._tracker = None  # a seek restarts the temporal smoothing
            self._sdr_reset()
        return GstBase.BaseTransform.do_sink_event(self, event)

    # ---- caps ---------------------------------------------------------------------------------------
    def do_transform_caps(self, direction, caps, filt):
        transfer = self.settings.transfer

        def to_raw(s):
            out = []
            for colour in _colour_kinds(s):
                for fmt in _FORMATS[(colour, transfer == "log")]:
                    n = Gst.Structure.new_empty("video/x-raw")
                    n.set_value("format", fmt)
                    copy_fields(s, n)
                    if transfer != "log":
                        n.set_value("colorimetry", COLORIMETRY[transfer])
                    out.append(n)
            return out

        def to_hdr(s):
            fmts = _field_values(s, "format")
            grey = set(LOG_FORMATS + HDR_FORMATS)
            kinds = (False, True) if fmts is None else tuple(dict.fromkeys(f not in grey for f in fmts))
            out = []
            for colour in kinds:
                n = Gst.Structure.new_empty(HDR_MEDIA_TYPE)
                n.set_value("layout", RGB_LAYOUT if colour else HDR_LAYOUT)
                copy_fields(s, n)
                out.append(n)
            return out

        return transform_caps_by_structure(caps, filt, to_raw if direction == Gst.PadDirection.SINK
                                           else to_hdr, self)

    def do_transform_size(self, direction, caps, size, othercaps):
        try:
            if direction == Gst.PadDirection.SINK:
                vi = GstVideo.VideoInfo.new_from_caps(othercaps)
                return (vi is not None), (vi.size if vi is not None else 0)
            info = HdrInfo.from_caps(othercaps, LAYOUTS)
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

    @guarded("set_caps", False)
    def do_set_caps(self, incaps, outcaps):
        self._in_info = info = HdrInfo.from_caps(incaps, LAYOUTS, element="nrtonemap")
        vi = GstVideo.VideoInfo.new_from_caps(outcaps)
        if vi is None:
            self.post_error(f"cannot parse output caps {outcaps.to_string()}", kind="format")
            return False
        fmt = vi.finfo.format
        p = self.settings
        transfer = p.transfer
        formats = _FORMATS[(info.colour, transfer == "log")]
        if vi.finfo.name not in formats:
            self.post_error(f"output format {vi.finfo.name} does not fit transfer={transfer} for "
                            f"{info.layout} frames (needs {' or '.join(formats)})", kind="format")
            return False
        self._out_dtype = np.uint8 if fmt in (GstVideo.VideoFormat.GRAY8, GstVideo.VideoFormat.RGB) \
            else np.dtype("<u2")
        self._byteswap = fmt == GstVideo.VideoFormat.GRAY16_BE
        self._out_transfer = transfer
        self._out_info = vi
        self._tracker = None
        self._sdr_reset()
        self._profile_gains = None
        if info.colour:
            self._profile_gains = self._read_profile_gains(info)
            from nrhdr_core import hdr_output, tonemap
            if transfer == "log":
                self.nr_warmup(tonemap.warmup_rgb, elements=True, operators=(p.operator,))
            else:
                self.nr_warmup(hdr_output.warmup_rgb, transfers=(transfer,), elements=True)
        self.gst_debug(f"caps: {incaps.to_string()} -> {outcaps.to_string()} (transfer={transfer})")
        return True

    def _read_profile_gains(self, info) -> tuple:
        """white-balance=profile: the white_balance of the profile the caps name; (1, 1, 1) without one."""
        if not info.profile:
            self.gst_info("the input caps name no profile: white-balance=profile applies no gains")
            return (1.0, 1.0, 1.0)
        prof = load_profile(info.profile, from_caps=True)
        return tuple(float(g) for g in getattr(prof, "white_balance", (1.0, 1.0, 1.0)))

    # ---- data ---------------------------------------------------------------------------------------
    def _sdr_reset(self) -> None:
        """Restart the temporal state: the automatic white, the local operator's statistics and the grey-world
        gains."""
        self._auto = None
        self._local = None
        self._grey = None
        self._auto_noted = False

    def _gains(self, p, rgb) -> tuple:
        """The white balance gains (R, G, B) of this frame (`white-balance`)."""
        from nrhdr_core import tonemap
        if p.white_balance == "none":
            return (1.0, 1.0, 1.0)
        if p.white_balance == "profile":
            return self._profile_gains or (1.0, 1.0, 1.0)
        if self._grey is None:
            self._grey = tonemap.GreyWorld(p.smoothing, self._in_info.white)
        self._grey.speed = p.smoothing
        return self._grey.update(rgb)

    def _colour(self, p, rgb, white, transfer, outbuf) -> None:
        """A colour frame into the output: RGB (log) or BT.2020 Y'CbCr (pq/hlg)."""
        from nrhdr_core import hdr_output, tonemap
        from nrhdr_core.scratch import planes
        vi = self._out_info
        gains = self._gains(p, rgb)
        offsets, strides = _mapped_planes(outbuf, vi)
        ok, mi = outbuf.map(RW)
        if not ok:
            raise RuntimeError("cannot map the output video buffer for writing")
        try:
            frame = np.ndarray((outbuf.get_size(),), np.uint8, buffer=mi.data)
            h, w = vi.height, vi.width
            if transfer == "log":
                out = np.ndarray((h, w, 3), np.uint8, frame, offsets[0], (strides[0], 3, 1))
                if p.operator == "local":
                    if self._local is None:
                        self._local = tonemap.LocalTonemap(p.smoothing)
                    self._local.speed = p.smoothing
                    self._local.rgb(rgb, white, p.exposure, p.contrast, gains, p.saturation, out=out)
                else:
                    tonemap.tonemap_rgb(rgb, white, "log", gains, p.exposure, p.contrast, p.saturation, out=out)
            else:
                codes = planes("nrtonemap.rgb-codes", (h, w), lambda: np.empty((3, h, w), np.uint16))
                tonemap.hdr_encode_rgb(rgb, white, transfer, gains, "bt2020", p.reference_white, p.exposure,
                                       out=codes, peak=p.peak, source_peak=self._source_peak(p, white, transfer))
                hdr_output.ycbcr_frame(codes, frame, offsets, strides,
                                       subsample=vi.finfo.format == GstVideo.VideoFormat.I420_10LE)
        finally:
            outbuf.unmap(mi)

    def _auto_white(self, p, values) -> float:
        from nrhdr_core import tonemap
        if self._auto is None:
            self._auto = tonemap.AutoWhite(p.smoothing, p.contrast)
        self._auto.speed, self._auto.contrast = p.smoothing, p.contrast
        return self._auto.update(values)

    def _sdr(self, p, values, white, out) -> None:
        """transfer=log: the SDR operator into the mapped output."""
        from nrhdr_core import tonemap
        if p.operator == "local":
            if self._local is None:
                self._local = tonemap.LocalTonemap(p.smoothing)
            self._local.speed = p.smoothing
            self._local(values, white, exposure_stops=p.exposure, contrast=p.contrast, out=out)
        else:
            tonemap.log_tonemap(values, white, exposure_stops=p.exposure, contrast=p.contrast, out=out)

    def _white(self, p, values, hdr: bool = False) -> float:
        """The normaliser: full scale of the log curve, or (hdr) the value shown at reference white."""
        from nrhdr_core import tonemap
        if p.normalise == "auto" or (p.normalise == "caps" and not hdr and self._in_info.white is None):
            if hdr:
                raise ValueError("normalise=auto is for transfer=log (HDR output needs the caps' diffuse-white "
                                 "or normalise=fixed white=...)")
            if p.normalise == "caps" and not self._auto_noted:
                self._auto_noted = True
                self.gst_info("the input caps have no 'white' field: automatic white (normalise=auto)")
            return self._auto_white(p, values)
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

    def _source_peak(self, p, white: float, transfer: str) -> float:
        """Display light of the brightest value the sensor gives (the caps' white) at this mapping: where the
        EETF starts from; 10000 cd/m2 when the caps do not say."""
        from nrhdr_core import tonemap
        if p.peak <= 0:
            return 0.0
        info = self._in_info
        if info.white is None or info.diffuse_white is None:
            return tonemap.L_P
        top = white * info.white / info.diffuse_white
        return tonemap.peak_luminance(top, white, transfer, p.reference_white, p.exposure)

    @guarded(lambda self: f"frame {self._frames}", Gst.FlowReturn.ERROR)
    def do_transform(self, inbuf, outbuf):
        p = self.settings  # one read per frame: a consistent parameter set
        if self._in_info is None or self._out_info is None:
            self.post_error("no caps negotiated before the first buffer", kind="negotiation")
            return Gst.FlowReturn.NOT_NEGOTIATED
        from nrhdr_core import tonemap
        transfer = self._out_transfer
        t0 = time.perf_counter()
        if self._in_info.colour:
            with self.warnings_to_bus(), map_hdr(inbuf, self._in_info, write=False) as (values, _state):
                # normalise=auto / smoothed: statistics of the green plane (most of the luminance)
                white = self._white(p, values[1], hdr=transfer != "log")
                if not (math.isfinite(white) and white > 0):
                    raise ValueError(f"tone mapping white is {white}")
                self._colour(p, values, white, transfer, outbuf)
        else:
            with self.warnings_to_bus(), map_hdr(inbuf, self._in_info, write=False) as (values, _state), \
                    map_video(outbuf, self._out_info, self._out_dtype, write=True, exact=False) as out:
                white = self._white(p, values, hdr=transfer != "log")
                if not (math.isfinite(white) and white > 0):
                    raise ValueError(f"tone mapping white is {white}")
                # kernels write straight into the mapped output (strided rows are fine for numba)
                if transfer == "log":
                    self._sdr(p, values, white, out)
                else:
                    tonemap.hdr_encode(values, white, transfer, reference_white=p.reference_white,
                                       exposure_stops=p.exposure, out=out, peak=p.peak,
                                       source_peak=self._source_peak(p, white, transfer))
                    if self._byteswap:
                        out.byteswap(inplace=True)
        if self.gst_debug_enabled(Gst.DebugLevel.LOG):
            self.gst_log(f"frame {self._frames} pts {Gst.TIME_ARGS(inbuf.pts)}: {transfer} {p.operator} "
                         f"white={white:.6g} exposure={p.exposure:+.2f} in "
                         f"{(time.perf_counter() - t0) * 1e3:.2f} ms")
        self._frames += 1
        return Gst.FlowReturn.OK
