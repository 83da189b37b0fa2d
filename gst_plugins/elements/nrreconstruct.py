"""nrreconstruct: fills the missing pixels of HDR frames in place (paper 2.2, 2.4, 5); turns the mosaic frames
of a colour sensor into colour frames (docs/COLOUR.md "Caps and elements").

Monochrome frames: `nrhdr_core.reconstruction.reconstruct_frame` on the mapped frame, in place; known =
reason VALID; clipped pixels' values are lower bounds and too-dark pixels' upper bounds (`use-bounds`).
Filled pixels get the RECONSTRUCTED bit (their reason is kept).

Mosaic frames (caps field `cfa` = a Bayer phase): `nrhdr_core.demosaic.reconstruct_cfa` writes a colour
frame (`layout=rgb-f32-u8-planar`: R, G, B planes and the mosaic's state) into an output buffer from a pool,
one frame out per frame in, timestamps and flags copied. method=preview and fse (+ preset) and auto (the
same ladder) work; linear, nearest and temporal=on are monochrome only (an element error naming the
property).

`method` and `preset` can change while PLAYING: the streaming thread reads the settings snapshot once per
frame. Posts an element message "nrhdr-frame-stats" per frame when `post-stats` is on.

`temporal=on` (docs/TEMPORAL.md): `nrhdr_core.temporal.TemporalReconstructor`
instead, the previous output aligned by a motion estimate as prior and extra measurements where a per-block
consistency check trusts it; its state restarts on a flush, a new segment (seek), new caps, a change of
the reconstruction settings and stop.

Live (docs/ELEMENTS.md "Live operation"): QoS on by default and LATENCY answered with the processing time
(`LiveTiming`); `method=auto` picks per frame the most accurate rung of `nrhdr_core.realtime.LADDER` that
fits `budget-ms` (default 70 % of the frame period), with hysteresis (`nrhdr_core.realtime.AutoController`).
"""
from __future__ import annotations

import time

import numpy as np

from nrhdr_core.chain import MAX_TEMPORAL_BUDGET, TEMPORAL_BUDGET, TEMPORAL_MODES
from nrhdr_core.fse import FSE_PRESETS
from nrhdr_core.reconstruction import FUSIONS, METHODS

from ._common import (HDR_LAYOUT, LATENCY_PROP, LAYOUTS, RGB_LAYOUT, CapsError, GObject, Gst, GstBase, HdrInfo,
                      HdrPool, LiveTiming, NrElement, Prop, PropertyTable, copy_timestamps, debug_category, guarded,
                      hdr_transform_templates, load_profile, map_hdr, starting, transform_caps_by_structure)

BUDGET_SHARE = 0.7  # method=auto without budget-ms: this share of the frame period (the rest: other stages)
STATS_MESSAGE = "nrhdr-frame-stats"
COLOUR_METHODS = ("preview", "fse", "auto")   # the methods of a mosaic stream (demosaic.METHODS and auto)

PROPERTIES = PropertyTable("GstNrReconstruct", [
    Prop("method", METHODS + ("auto",), "fse", "Method",
         "Reconstruction method: 'fse' = Frequency Selective Extrapolation (paper, best), 'linear' = "
         "Delaunay-linear, 'nearest' = nearest known pixel, 'preview' = fast pull-push for live preview, "
         "'auto' = per frame the most accurate of fse best/balanced/fast/preview and preview that fits "
         "budget-ms. A colour mosaic (caps cfa) takes preview, fse and auto (docs/COLOUR.md)", playing=True),
    Prop("preset", tuple(FSE_PRESETS), "balanced", "Preset",
         "FSE parameter preset, speed against quality; ignored by other methods", playing=True),
    Prop("budget-ms", float, 0.0, "Time budget (ms)",
         "method=auto: milliseconds per frame the reconstruction may take; 0 = 70 % of the frame period of "
         "the caps (30 frames a second when the caps have no framerate)", minimum=0.0, maximum=60000.0,
         playing=True),
    Prop("use-bounds", bool, True, "Use bounds",
         "Keep reconstructed clipped pixels at or above their clip level and too-dark pixels at or below "
         "l_min x ND (the bounds their state implies)", playing=True),
    Prop("noise-fusion", FUSIONS, "auto", "Noise fusion",
         "How NOISY pixels (nrvalidity dark-policy=weighted) are fused with their noisy measurement: "
         "'accurate' = from the measured 3 x 3 neighbours and the pixel by inverse noise variance, 'fast' = "
         "the reconstruction and the pixel (about 25 % less time, about 0.3 dB lower in dark regions; "
         "docs/BENCHMARKS.md), 'auto' = fast for method=preview (live), accurate for the others",
         playing=True),
    Prop("temporal", TEMPORAL_MODES, "off", "Temporal",
         "'on' = the previous output, aligned by a motion estimate, is a prior for missing pixels and extra "
         "measurements for measured and noisy ones where a per-block check against the noise model trusts "
         "it; blocks that did not change reuse their result; measured pixels of trusted blocks become their "
         "recursive average (docs/TEMPORAL.md). Restarts on flush, seek, caps change and "
         "stop. Monochrome streams only", playing=True),
    Prop("temporal-budget", int, TEMPORAL_BUDGET, "Temporal budget",
         "temporal=on: the method's work a frame to refine a still shot, in blocks' worth (one 16 x 16 block "
         "every pixel of which is unknown, in a band: 348 unknown pixels' work), whatever the frame size. A "
         "shot's first frame (and a cut's) is the preview; from the next frame on, the still blocks below "
         "their temporal quality are reconstructed by the method (the least refined first, then the block "
         "rows where the preview stands in for the most missing pixels) while their work fits the budget, "
         "and kept once their measured pixels average 4 frames. The default keeps every frame of a static "
         "1080p shot at about the preview's cost; a larger frame takes more frames to reach its temporal "
         "quality (docs/TEMPORAL.md). Counted in work, not time: the output does not depend on the "
         "machine. 0 = no bound (the first frame by the method, every block that needs it every frame)",
         minimum=0, maximum=MAX_TEMPORAL_BUDGET, playing=True),
    Prop("post-stats", bool, False, "Post statistics",
         "Post an element message 'nrhdr-frame-stats' per frame (fields frame, missing = fraction of pixels "
         "reconstructed, method, seconds; with temporal=on also the blocks' shares reused, refreshed, fresh, "
         "refined (reconstructed by the method), pending (reused at less than their temporal quality), work "
         "(the method's work in blocks' worth, the unit of temporal-budget), the global motion motion-x, "
         "motion-y and cut). Off by default: an application that never reads the "
         "bus would keep every message", playing=True),
    LATENCY_PROP,
])


class NrReconstruct(NrElement, LiveTiming, GstBase.BaseTransform):
    __gtype_name__ = "GstNrReconstruct"
    PROPERTIES = PROPERTIES
    DEBUG_CATEGORY = debug_category("nrreconstruct", "nrhdr missing-pixel reconstruction")
    __gstmetadata__ = (
        "nrhdr missing-pixel reconstruction",
        "Filter/Effect/Video",
        "Fills the missing (clipped, too dark, discarded) pixels of HDR frames (other/x-nrhdr) by "
        "Frequency Selective Extrapolation, linear (Delaunay) or nearest interpolation, or a fast "
        "pull-push preview; turns a colour sensor's mosaic frames into RGB frames; posts "
        "'nrhdr-frame-stats' element messages",
        "nrhdr project",
    )
    __gsttemplates__ = hdr_transform_templates(src_layouts=LAYOUTS)

    do_gst_base_transform_query = LiveTiming.nr_live_query

    def __init__(self):
        super().__init__()
        self.nr_live_init()
        self._auto = None
        self._last_pts, self._skipped = None, 0
        self._info = None
        self._out_info = None
        self._pool = None
        self._warm_cfa = set()
        self._noise = None
        self._frames = 0
        self._temporal = self._temporal_key = None
        self.set_in_place(True)
        self.set_passthrough(False)

    # ---- state --------------------------------------------------------------------------------------
    @starting
    def do_start(self):
        from nrhdr_core import chain, realtime
        s = self.settings
        rungs = ([(r.method, r.preset or s.preset) for r in realtime.LADDER] if s.method == "auto"
                 else [(s.method, s.preset)])
        self.nr_warmup(chain.warmup, [chain.ChainSettings(method=m, preset=p, use_bounds=s.use_bounds,
                                                          noise_fusion=s.noise_fusion, dark_policy=d,
                                                          temporal=s.temporal, temporal_budget=s.temporal_budget)
                                      for m, p in rungs for d in chain.DARK_POLICIES],
                       stages=("reconstruction",), elements=True)
        self._auto = realtime.AutoController()
        self.nr_live_reset()
        self._last_pts, self._skipped = None, 0
        self._frames = 0
        self._temporal = None
        return True

    def do_stop(self):
        self._info = self._out_info = None
        self._temporal = None
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        return True

    def do_sink_event(self, event):
        if event.type in (Gst.EventType.FLUSH_STOP, Gst.EventType.SEGMENT):
            self._temporal = None       # a seek or a new segment: the past is not this stream's
        return GstBase.BaseTransform.do_sink_event(self, event)

    # ---- caps ---------------------------------------------------------------------------------------
    def do_transform_caps(self, direction, caps, filt):
        """Sink to src: a mosaic (cfa a Bayer phase) becomes a colour frame, a frame without cfa (or cfa none)
        stays what it is; src to sink: a colour frame comes from a mosaic, a one-plane frame from itself."""
        def to_src(s):
            layout = s.get_string("layout") if s.has_field("layout") else None
            if layout not in (None, HDR_LAYOUT) or not s.has_field("cfa") or s.get_string("cfa") == "none":
                return [s.copy()]       # monochrome (or a layout refused by name in set_caps)
            rgb = s.copy()
            rgb.set_value("layout", RGB_LAYOUT)
            return [rgb]

        def to_sink(s):
            if not (s.has_field("layout") and s.get_string("layout") == RGB_LAYOUT):
                return [s.copy()]
            n, bare = s.copy(), s.copy()
            n.set_value("layout", HDR_LAYOUT)
            bare.remove_field("layout")     # upstream caps may omit the layout (f32-u8-planar)
            return [n, bare]

        sink = direction == Gst.PadDirection.SINK
        out = transform_caps_by_structure(caps, filt, to_src if sink else to_sink, self)
        self.gst_log(f"transform_caps {direction.value_nick}: {caps.to_string()} -> {out.to_string()}")
        return out

    @guarded("set_caps", False)
    def do_set_caps(self, incaps, outcaps):
        info = HdrInfo.from_caps(incaps, element="nrreconstruct")
        out = HdrInfo.from_caps(outcaps, LAYOUTS, element="nrreconstruct")
        if out.colour != info.mosaic:
            raise CapsError(f"nrreconstruct turns a mosaic frame (caps cfa=rggb|bggr|grbg|gbrg) into a "
                            f"{RGB_LAYOUT} frame and a monochrome frame into itself: cannot make "
                            f"{out.layout} from {incaps.to_string()}")
        colour_before = self._info is not None and self._info.mosaic
        self._info, self._out_info = info, out
        self._noise = None              # the profile may have changed with the caps
        self._temporal = None
        if info.mosaic:
            refusal = self._colour_refusal(self.settings)
            if refusal:
                self.post_error(refusal, kind="settings")
                return False
            self._pool = HdrPool.for_info(self._pool, out)
            self._warm_colour(info.cfa)
        if colour_before != info.mosaic:
            from nrhdr_core import realtime
            self._auto = realtime.AutoController()  # the two paths cost differently
        self.set_in_place(not info.mosaic)
        self.gst_debug(f"caps {incaps.to_string()} -> {outcaps.to_string()}")
        return True

    def _colour_refusal(self, p) -> str | None:
        """Why the settings `p` cannot reconstruct this mosaic stream (None when they can)."""
        cfa = self._info.cfa
        if p.temporal == "on":
            return (f"temporal=on works on monochrome streams only; this stream is a colour mosaic (caps "
                    f"cfa={cfa}): set temporal=off")
        if p.method not in COLOUR_METHODS:
            return (f"method={p.method} works on monochrome streams only; a colour mosaic (caps cfa={cfa}) "
                    f"takes method={', '.join(COLOUR_METHODS)}")
        return None

    def _warm_colour(self, cfa: str) -> None:
        """Compile the demosaic kernels the settings use (once per CFA and run; numba's cache after)."""
        if cfa in self._warm_cfa:
            return
        from nrhdr_core import chain, realtime
        s = self.settings
        rungs = ([(r.method, r.preset or s.preset) for r in realtime.LADDER] if s.method == "auto"
                 else [(s.method, s.preset)])
        self.nr_warmup(chain.warmup, [chain.ChainSettings(method=m, preset=p, use_bounds=s.use_bounds,
                                                          noise_fusion=s.noise_fusion, dark_policy=d)
                                      for m, p in rungs for d in chain.DARK_POLICIES],
                       stages=("reconstruction",), elements=True, cfa=cfa)
        self._warm_cfa.add(cfa)

    @guarded("prepare_output_buffer", (Gst.FlowReturn.ERROR, None))
    def do_prepare_output_buffer(self, inbuf):
        """A colour frame from the pool (timestamps and flags of the input); monochrome frames are
        reconstructed in place (BaseTransform's own buffer handling)."""
        if self._info is None or not self._info.mosaic:
            ret, buf = GstBase.BaseTransform.do_prepare_output_buffer(self, inbuf)
            return ret, buf
        out = self._pool.acquire()
        copy_timestamps(inbuf, out)
        return Gst.FlowReturn.OK, out

    # ---- data ---------------------------------------------------------------------------------------
    @guarded(lambda self: f"frame {self._frames} (method={self.settings.method}, preset={self.settings.preset})",
             Gst.FlowReturn.ERROR)
    def do_transform(self, inbuf, outbuf):
        """A mosaic frame to a colour frame (`demosaic.reconstruct_cfa`): the mosaic's state copied into the
        output, its RECONSTRUCTED bits set where a photosite's own channel was filled."""
        p = self.settings  # one read per frame: a consistent parameter set
        if self._info is None or not self._info.mosaic:
            self.post_error("no mosaic caps negotiated before the first buffer", kind="negotiation")
            return Gst.FlowReturn.NOT_NEGOTIATED
        refusal = self._colour_refusal(p)
        if refusal:
            self.post_error(refusal, kind="settings")
            return Gst.FlowReturn.ERROR
        from nrhdr_core import demosaic
        from nrhdr_core.states import REASON_MASK, RECONSTRUCTED, VALID
        self._count_gap(inbuf)
        t0 = time.perf_counter()
        method, preset, rung, budget = p.method, p.preset, None, None
        counted = p.method == "auto" or p.post_stats or self.gst_debug_enabled(Gst.DebugLevel.LOG)
        n_miss = 0
        with self.warnings_to_bus(), map_hdr(inbuf, self._info, write=False) as (values, state_in), \
                map_hdr(outbuf, self._out_info, write=True) as (rgb, state):
            if counted:   # the photosites reconstruct_cfa fills: missing and not yet RECONSTRUCTED
                n_miss = int(np.count_nonzero(((state_in & REASON_MASK) != VALID)
                                              & ((state_in & RECONSTRUCTED) == 0)))
            if p.method == "auto":
                budget = self._budget(p)
                rung = self._auto.choose(budget, n_miss / float(self._info.pixels))
                method, preset = rung.method, rung.preset or p.preset
            state[...] = state_in
            demosaic.reconstruct_cfa(values, state, self._info.cfa, method=method, preset=preset,
                                     use_bounds=p.use_bounds, noise=self._noise_model(), fusion=p.noise_fusion,
                                     out=rgb)
        self._frame_done(inbuf, p, n_miss, time.perf_counter() - t0, method, preset, rung, budget)
        return Gst.FlowReturn.OK

    @guarded(lambda self: f"frame {self._frames} (method={self.settings.method}, preset={self.settings.preset})",
             Gst.FlowReturn.ERROR)
    def do_transform_ip(self, buf):
        p = self.settings  # one read per frame: a consistent parameter set
        if self._info is None:
            self.post_error("no caps negotiated before the first buffer", kind="negotiation")
            return Gst.FlowReturn.NOT_NEGOTIATED
        from nrhdr_core import reconstruction
        self._count_gap(buf)
        t0 = time.perf_counter()
        picked = {"method": p.method, "preset": p.preset, "rung": None, "budget": None}

        def choose(share):  # method=auto: the most accurate rung that fits the frame period
            budget = self._budget(p)
            rung = self._auto.choose(budget, share)
            picked.update(method=rung.method, preset=rung.preset or p.preset, rung=rung, budget=budget)
            return picked["method"], picked["preset"]

        tr = self._temporal_for(p)
        work = None
        with self.warnings_to_bus(), map_hdr(buf, self._info, write=True) as (values, state):
            method = choose if p.method == "auto" else p.method
            if tr is not None:
                tr.method = method
                work = tr.process(values, state, noise=self._noise_model())
                n_miss = work["missing"]
            else:
                # one fused pass for known mask + bounds, in place, measured pixels untouched; NOISY pixels
                # fused with the profile's noise model; a fixed method goes by name
                n_miss = reconstruction.reconstruct_frame(values, state, method=method, preset=p.preset,
                                                          use_bounds=p.use_bounds, noise=self._noise_model(),
                                                          fusion=p.noise_fusion)
        method, preset, rung, budget = picked["method"], picked["preset"], picked["rung"], picked["budget"]
        self._frame_done(buf, p, n_miss, time.perf_counter() - t0, method, preset, rung, budget, work)
        return Gst.FlowReturn.OK

    def _frame_done(self, buf, p, n_miss, dt, method, preset, rung, budget, work=None) -> None:
        """After a frame: the LOG line, method=auto's measurement, the stats message, the frame count."""
        share = n_miss / float(self._info.pixels)
        if self.gst_debug_enabled(Gst.DebugLevel.LOG):  # per-frame line (GST_DEBUG=nrreconstruct:6)
            self.gst_log(f"frame {self._frames} pts {Gst.TIME_ARGS(buf.pts)}: " + (
                f"{n_miss} missing pixels ({100.0 * share:.2f} %) filled by method={method} preset={preset} "
                f"in {dt * 1e3:.2f} ms" if n_miss else f"skipped: no pixel missing ({dt * 1e3:.2f} ms)"))
        if rung is not None:
            self._auto.record(rung, dt, share, budget)
        if p.post_stats:
            chosen = "none" if not n_miss else (f"fse/{preset}" if method == "fse" else method)
            self._post_frame_stats(share, method, dt, chosen, preset if method == "fse" else "", work)
        self._frames += 1

    def _temporal_for(self, p):
        """The stream's TemporalReconstructor with temporal=on (None off); a new one (no past) when the
        settings it reconstructs with changed."""
        if p.temporal != "on":
            self._temporal = None
            return None
        key = (p.method, p.preset, p.use_bounds, p.noise_fusion)
        if self._temporal is None or self._temporal_key != key:
            from nrhdr_core.temporal import TemporalReconstructor
            self._temporal = TemporalReconstructor(method="fse" if p.method == "auto" else p.method,
                                                   preset=p.preset, use_bounds=p.use_bounds,
                                                   fusion=p.noise_fusion, budget=p.temporal_budget)
            self._temporal_key = key
        self._temporal.options["budget"] = int(p.temporal_budget)     # takes effect from this frame
        return self._temporal

    def _count_gap(self, buf) -> None:
        """Frames skipped upstream (QoS drops in earlier elements, frames lost at a live source): PTS
        gaps of more than one frame duration."""
        pts, dur = buf.pts, buf.duration
        last, self._last_pts = self._last_pts, pts
        if (last is None or pts == Gst.CLOCK_TIME_NONE or dur == Gst.CLOCK_TIME_NONE or dur == 0
                or pts <= last):
            return
        self._skipped += max(int(round((pts - last) / dur)) - 1, 0)

    def _budget(self, p) -> float:
        """Seconds per frame for method=auto: budget-ms, else BUDGET_SHARE of the frame period."""
        if p.budget_ms > 0:
            return p.budget_ms / 1e3
        i = self._info
        period = i.fps_d / i.fps_n if i.fps_n > 0 else 1 / 30
        return BUDGET_SHARE * period

    def _noise_model(self):
        """The noise model NOISY pixels (nrvalidity dark-policy=weighted) are fused with: the profile
        named in the caps, else the default sensor's noise. Loaded once per caps."""
        if self._noise is None:
            from nrhdr_core import validity
            noise = None
            if self._info.profile:
                try:
                    noise = load_profile(self._info.profile, from_caps=True)
                except ValueError:
                    noise = None
            self._noise = noise if noise is not None else validity.default_noise()
        return self._noise

    def _post_frame_stats(self, missing: float, method: str, seconds: float, chosen: str = "",
                          preset: str = "", work: dict | None = None) -> None:
        """Fields: the method (and fse preset) used for this frame, late frames QoS dropped before it,
        frames skipped upstream, and the processing latency answered to the LATENCY query; with temporal=on
        the work of `TemporalReconstructor.process`: shares of blocks reused, refreshed (reconstructed and
        fused with their past), fresh (reconstructed alone), refined (reconstructed by the method),
        pending (reused before their temporal quality), the method's work in blocks' worth (the unit of
        temporal-budget), the global motion and whether the frame was a cut."""
        s = Gst.Structure.new_empty(STATS_MESSAGE)
        s.set_value("frame", GObject.Value(GObject.TYPE_UINT64, self._frames))
        s.set_value("missing", GObject.Value(GObject.TYPE_DOUBLE, float(missing)))
        s.set_value("method", method)
        s.set_value("seconds", GObject.Value(GObject.TYPE_DOUBLE, float(seconds)))
        s.set_value("preset", preset)
        s.set_value("chosen", chosen)
        s.set_value("qos-dropped", GObject.Value(GObject.TYPE_UINT64, self.nr_qos_skipped()))
        s.set_value("skipped", GObject.Value(GObject.TYPE_UINT64, self._skipped + self.nr_qos_skipped()))
        s.set_value("latency", GObject.Value(GObject.TYPE_DOUBLE, self.nr_processing_latency() / 1e9))
        s.set_value("temporal", "off" if work is None else "on")
        if work is not None:
            from nrhdr_core.temporal import block_worth
            alone = work["fresh"] + work["no_prior"] + work["no_evidence"]
            for name, v in (("reused", work["reused"]), ("refreshed", work["refreshed"]), ("fresh", alone),
                            ("refined", work["refined"]), ("pending", work["pending"]),
                            ("work", work["work"] / block_worth(int(self._temporal.options["block"]))),
                            ("motion-x", work["motion"][1]), ("motion-y", work["motion"][0])):
                s.set_value(name, GObject.Value(GObject.TYPE_DOUBLE, float(v)))
            s.set_value("cut", GObject.Value(GObject.TYPE_BOOLEAN, bool(work["cut"])))
        self.post_message(Gst.Message.new_element(self, s))
