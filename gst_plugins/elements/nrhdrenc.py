"""nrhdrenc: linear HDR frames (`other/x-nrhdr`) -> HEVC Main 10 HDR video with all its signalling
(docs/HDR-OUTPUT.md). A bin: `nrtonemap transfer=pq|hlg` (diffuse white at `reference-white`, highlights
rolled off to `peak` by the BT.2390 EETF) ! videoconvert ! I420_10LE with colorimetry bt2100-pq / bt2100-hlg
and, for PQ, the ST 2086 mastering display and CTA-861.3 content light level ! x265enc (constant quality
`crf`, `speed-preset`) ! h265parse. Put a muxer after it (mp4mux; matroskamux with `matroska=true`).

Live, the frames are not known in advance: MaxCLL / MaxFALL are the `max-cll` / `max-fall` properties, or
(0) estimated from the caps (`nrhdr_core.hdr_output.estimate_light_levels`: MaxCLL the brightest light the
sensor's white reaches, at most `peak`; MaxFALL the reference white). `nrhdr hdr10` measures them over a file.

Colour frames (layout rgb-f32-u8-planar): white balanced (`white-balance`), BT.709 camera RGB converted to
BT.2020 primaries, PQ / HLG per channel and BT.2020 non-constant-luminance Y'CbCr 4:2:0 by nrtonemap itself
(`nrhdr_core.hdr_output.ycbcr_frame`); videoconvert passes its I420_10LE through.
"""
from __future__ import annotations

import weakref

from nrhdr_core import hdr_output
from nrhdr_core.tonemap import REFERENCE_WHITE_NITS, TRANSFERS

from ._common import LAYOUTS, Gst, HdrInfo, NrElement, Prop, PropertyTable, debug_category, hdr_template_caps

PROPERTIES = PropertyTable("GstNrHdrEnc", [
    Prop("transfer", TRANSFERS, "pq", "Transfer function",
         "'pq' = HDR10 (SMPTE ST 2084, with ST 2086 and CTA-861.3 metadata); 'hlg' = ARIB STD-B67 (no static "
         "metadata)"),
    Prop("reference-white", float, REFERENCE_WHITE_NITS, "Reference white (cd/m2)",
         "Display luminance of the scene's diffuse white (the caps' diffuse-white; ITU-R BT.2408: 203)",
         minimum=1.0, maximum=10000.0),
    Prop("exposure", float, 0.0, "Exposure", "Exposure correction in stops (x 2^exposure)",
         minimum=-20.0, maximum=20.0),
    Prop("white-balance", ("profile", "grey-world", "none"), "profile", "White balance",
         "Colour frames: 'profile' = the gains of the profile named in the caps (none without one); "
         "'grey-world' = the frame's mean colour made grey, smoothed over time; 'none' = camera RGB"),
    Prop("peak", float, hdr_output.DEFAULT_PEAK, "Peak (cd/m2)",
         "Mastering display peak: light above it is rolled off by the BT.2390 EETF (0 = none: PQ clips at "
         "10000)", minimum=0.0, maximum=10000.0),
    Prop("min-luminance", float, hdr_output.DEFAULT_MIN_LUMINANCE, "Mastering black (cd/m2)",
         "Mastering display minimum luminance (ST 2086)", minimum=0.0, maximum=100.0),
    Prop("primaries", tuple(hdr_output.PRIMARIES), "bt2020", "Mastering primaries",
         "Mastering display primaries (ST 2086): BT.2020 or P3-D65, D65 white"),
    Prop("max-cll", int, 0, "MaxCLL (cd/m2)",
         "CTA-861.3 maximum content light level; 0 = estimate from the caps' white (at most peak)",
         minimum=0, maximum=65535),
    Prop("max-fall", int, 0, "MaxFALL (cd/m2)",
         "CTA-861.3 maximum frame-average light level; 0 = estimate (the reference white, at most MaxCLL)",
         minimum=0, maximum=65535),
    Prop("crf", float, float(hdr_output.DEFAULT_CRF), "Constant quality",
         "x265 crf (lower = better and bigger; default chosen by measurement, docs/BENCHMARKS.md)",
         minimum=0.0, maximum=51.0),
    Prop("speed-preset", hdr_output.SPEED_PRESETS, hdr_output.DEFAULT_SPEED_PRESET, "x265 speed preset",
         "x265 preset: speed against compression at the same quality"),
    Prop("x265-options", str, "", "More x265 options", "key=value:key=value appended to the crf (e.g. "
         "lossless=1, keyint=60)"),
    Prop("matroska", bool, False, "Matroska follows",
         "matroskamux follows: the caps sent downstream carry the mastering luminance x5, which GStreamer "
         "1.22's matroskamux divides back into its Colour element (the stream's SEI keeps the true values)"),
])


class NrHdrEnc(NrElement, Gst.Bin):
    __gtype_name__ = "GstNrHdrEnc"
    PROPERTIES = PROPERTIES
    DEBUG_CATEGORY = debug_category("nrhdrenc", "nrhdr HDR10 / HLG encoder bin")
    __gstmetadata__ = (
        "nrhdr HDR10 / HLG encoder",
        "Codec/Encoder/Video",
        "Linear HDR frames (other/x-nrhdr) to HEVC Main 10 (x265enc) with BT.2020 / PQ or HLG / BT.2020 NCL / "
        "limited range and, for PQ, ST 2086 mastering display and CTA-861.3 MaxCLL / MaxFALL; colour frames "
        "converted from BT.709 to BT.2020 primaries",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS,
                            hdr_template_caps(layouts=LAYOUTS)),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS,
                            Gst.Caps.from_string("video/x-h265, stream-format=(string){ hvc1, hev1, "
                                                 "byte-stream }, alignment=(string)au")),
    )

    # The children are looked up by name, never kept as Python attributes, and the caps probe holds a weak
    # reference: a Python reference from the bin to its children (or a bound method on a child's pad) is a
    # cycle through C that keeps the bin alive after its pipeline is gone.
    _tone = property(lambda self: self.get_by_name("tone"))
    _conv = property(lambda self: self.get_by_name("conv"))
    _filter = property(lambda self: self.get_by_name("filter"))
    _enc = property(lambda self: self.get_by_name("enc"))
    _parse = property(lambda self: self.get_by_name("parse"))
    _setter = property(lambda self: self.get_by_name("setter"))

    def __init__(self):
        super().__init__()
        from .nrtonemap import NrTonemap
        tone = NrTonemap()
        tone.set_property("name", "tone")
        made = [(n, f, Gst.ElementFactory.make(f, n)) for n, f in (
            ("conv", "videoconvert"), ("filter", "capsfilter"), ("enc", "x265enc"), ("parse", "h265parse"),
            ("setter", "capssetter"))]
        self._missing = [f for _, f, e in made if e is None]
        sink = Gst.GhostPad.new_no_target_from_template("sink", self.get_pad_template("sink"))
        src = Gst.GhostPad.new_no_target_from_template("src", self.get_pad_template("src"))
        self.add_pad(sink)
        self.add_pad(src)
        if self._missing:
            return
        chain = [tone] + [e for _, _, e in made]
        chain[1].set_property("dither", 0)           # none: the 10-bit codes pass exactly
        for e in chain:
            self.add(e)
        for a, b in zip(chain, chain[1:]):
            a.link(b)
        sink.set_target(tone.get_static_pad("sink"))
        src.set_target(chain[-1].get_static_pad("src"))
        tone.get_static_pad("sink").add_probe(Gst.PadProbeType.EVENT_DOWNSTREAM, _caps_probe, weakref.ref(self))
        del tone, chain, made

    def _configure(self) -> None:
        """Children's settings from this element's properties (before any caps)."""
        p = self.settings
        self._tone.set_property("transfer", p.transfer)
        self._tone.set_property("reference-white", p.reference_white)
        self._tone.set_property("exposure", p.exposure)
        self._tone.set_property("white-balance", p.white_balance)
        self._tone.set_property("peak", p.peak)
        self._enc.set_property("speed-preset", p.speed_preset)
        opts = f"crf={p.crf:g}" + (f":{p.x265_options}" if p.x265_options else "")
        self._enc.set_property("option-string", opts)
        self._filter.set_property("caps", Gst.Caps.from_string(hdr_output.encoder_caps(p.transfer)))
        self._setter.set_property("caps", Gst.Caps.from_string("video/x-h265"))

    def _on_event(self, pad, info):
        """On the input caps: the static metadata (given, or estimated from the caps' white) into the caps
        x265enc is given (and the muxer's form of them into capssetter)."""
        ev = info.get_event()
        if ev is None or ev.type != Gst.EventType.CAPS:
            return Gst.PadProbeReturn.OK
        try:
            info = HdrInfo.from_caps(ev.parse_caps(), LAYOUTS, element="nrhdrenc")
            hdr_output.check_encode_size(info.width, info.height, "nrhdrenc")
            self._set_metadata(info)
        except Exception as e:  # noqa: BLE001
            self.post_exception("caps", e)
            return Gst.PadProbeReturn.DROP
        return Gst.PadProbeReturn.OK

    def _set_metadata(self, info) -> None:
        p = self.settings
        md = levels = None
        if p.transfer == "pq":
            cll, fall = p.max_cll, p.max_fall
            if not (cll and fall):
                if info.white is None or info.diffuse_white is None:
                    raise ValueError("max-cll / max-fall are 0 (estimate) but the input caps have no white and "
                                     "diffuse-white (put nrvalidity upstream, or set max-cll and max-fall)")
                est = hdr_output.estimate_light_levels(info.white, info.diffuse_white, "pq", p.reference_white,
                                                       p.exposure, p.peak)
                cll = cll or est[0]
                fall = fall or min(est[1], cll)
            md = hdr_output.MasteringDisplay(p.primaries, p.peak if p.peak > 0 else 10000.0, p.min_luminance)
            levels = (cll, fall)
            if p.matroska:
                self._setter.set_property("caps", Gst.Caps.from_string(hdr_output.matroska_caps(md)))
            self.gst_debug(f"metadata: mastering {md.caps_field()}, MaxCLL {cll}, MaxFALL {fall}")
        self._filter.set_property("caps", Gst.Caps.from_string(hdr_output.encoder_caps(p.transfer, md, levels)))

    def do_change_state(self, transition):
        if transition == Gst.StateChange.NULL_TO_READY:
            self.reset_errors()
            if self._missing:
                self.post_error(f"GStreamer elements {', '.join(self._missing)} missing: install "
                                f"gstreamer1.0-plugins-bad (x265enc, h265parse) and -good (capssetter)",
                                kind="not-found")
                return Gst.StateChangeReturn.FAILURE
            errors = self.settings_errors()
            if errors:
                self.post_error("; ".join(errors), kind="settings")
                return Gst.StateChangeReturn.FAILURE
            try:
                self._configure()
            except Exception as e:  # noqa: BLE001
                self.post_exception("start", e)
                return Gst.StateChangeReturn.FAILURE
        return Gst.Bin.do_change_state(self, transition)


def _caps_probe(pad, info, ref):
    el = ref()
    return el._on_event(pad, info) if el is not None else Gst.PadProbeReturn.OK
