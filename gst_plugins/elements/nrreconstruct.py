"""nrreconstruct: fills the missing pixels of HDR frames in place (paper 2.2, 2.4, 5).

`nrhdr_core.reconstruction.reconstruct_frame` on the mapped frame; known = reason VALID; clipped pixels'
values are lower bounds and too-dark pixels' upper bounds (`use-bounds`). Filled pixels get the
RECONSTRUCTED bit (their reason is kept). `method` and `preset` can change while PLAYING: the streaming
thread reads the settings snapshot once per frame. Posts an element message "nrhdr-frame-stats" per frame
when `post-stats` is on.

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

from nrhdr_core.chain import TEMPORAL_MODES
from nrhdr_core.fse import FSE_PRESETS
from nrhdr_core.reconstruction import FUSIONS, METHODS

from ._common import (LATENCY_PROP, GObject, Gst, GstBase, HdrInfo, LiveTiming, NrElement, Prop, PropertyTable,
                      debug_category, guarded, hdr_transform_templates, load_profile, map_hdr, starting)

BUDGET_SHARE = 0.7  # method=auto without budget-ms: this share of the frame period (the rest: other stages)
STATS_MESSAGE = "nrhdr-frame-stats"

PROPERTIES = PropertyTable("GstNrReconstruct", [
    Prop("method", METHODS + ("auto",), "fse", "Method",
         "Reconstruction method: 'fse' = Frequency Selective Extrapolation (paper, best), 'linear' = "
         "Delaunay-linear, 'nearest' = nearest known pixel, 'preview' = fast pull-push for live preview, "
         "'auto' = per frame the most accurate of fse best/balanced/fast/preview and preview that fits "
         "budget-ms", playing=True),
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
         "stop", playing=True),
    Prop("post-stats", bool, False, "Post statistics",
         "Post an element message 'nrhdr-frame-stats' per frame (fields frame, missing = fraction of pixels "
         "reconstructed, method, seconds; with temporal=on also the blocks' shares reused, refreshed, fresh, "
         "the global motion motion-x, motion-y and cut). Off by default: an application that never reads the "
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
        "pull-push preview; posts 'nrhdr-frame-stats' element messages",
        "nrhdr project",
    )
    __gsttemplates__ = hdr_transform_templates()

    do_gst_base_transform_query = LiveTiming.nr_live_query

    def __init__(self):
        super().__init__()
        self.nr_live_init()
        self._auto = None
        self._last_pts, self._skipped = None, 0
        self._info = None
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
                                                          temporal=s.temporal)
                                      for m, p in rungs for d in chain.DARK_POLICIES],
                       stages=("reconstruction",), elements=True)
        self._auto = realtime.AutoController()
        self.nr_live_reset()
        self._last_pts, self._skipped = None, 0
        self._frames = 0
        self._temporal = None
        return True

    def do_stop(self):
        self._info = None
        self._temporal = None
        return True

    def do_sink_event(self, event):
        if event.type in (Gst.EventType.FLUSH_STOP, Gst.EventType.SEGMENT):
            self._temporal = None       # a seek or a new segment: the past is not this stream's
        return GstBase.BaseTransform.do_sink_event(self, event)

    @guarded("set_caps", False)
    def do_set_caps(self, incaps, outcaps):
        self._info = HdrInfo.from_caps(incaps, element="nrreconstruct")
        self._noise = None              # the profile may have changed with the caps
        self._temporal = None
        self.gst_debug(f"caps {incaps.to_string()}")
        return True

    # ---- data ---------------------------------------------------------------------------------------
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
        share = n_miss / float(self._info.pixels)
        dt = time.perf_counter() - t0
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
        return Gst.FlowReturn.OK

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
                                                   fusion=p.noise_fusion)
            self._temporal_key = key
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
        fused with their past), fresh (reconstructed alone), the global motion and whether the frame was a
        cut."""
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
            alone = work["fresh"] + work["no_prior"] + work["no_evidence"]
            for name, v in (("reused", work["reused"]), ("refreshed", work["refreshed"]), ("fresh", alone),
                            ("motion-x", work["motion"][1]), ("motion-y", work["motion"][0])):
                s.set_value(name, GObject.Value(GObject.TYPE_DOUBLE, float(v)))
            s.set_value("cut", GObject.Value(GObject.TYPE_BOOLEAN, bool(work["cut"])))
        self.post_message(Gst.Message.new_element(self, s))
