"""Live operation of the processing BaseTransforms (docs/ELEMENTS.md "Live operation"): QoS, the
processing latency answered to the LATENCY query, and reports of numba compilations."""
from __future__ import annotations

import time
import weakref

from ._gst import Gst, GstBase
from ._props import Prop

LATENCY_PROP = Prop(
    "processing-latency", float, -1.0, "Processing latency",
    "Milliseconds this element adds to the pipeline latency (LATENCY query); -1 = a running estimate (95th "
    "percentile of the last 32 frames x 1.2), posting a LATENCY message when it grows by more than 25 %",
    minimum=-1.0, maximum=60000.0, playing=True)


class LiveTiming:
    """Mixin for the processing BaseTransforms:

    - QoS on by default (`qos` property of BaseTransform): late buffers are dropped before `transform`.
    - Per-frame processing time, measured between a sink-pad and a src-pad buffer probe, feeds a running
      estimate (`nrhdr_core.realtime.FrameTimes`); the LATENCY query answers upstream's latency plus
      that estimate, or the `processing-latency` property when >= 0; a LATENCY message is posted when
      the estimate grows by more than 25 %, so the pipeline recomputes its latency.
    - `nr_warmup(fn)`: run a core warm-up and report numba compilations (cache misses) with a Gst INFO
      log line and an element INFO message instead of stalling silently.

    A class opts in with `LATENCY_PROP` in its property table, `do_gst_base_transform_query =
    LiveTiming.nr_live_query` in its body and `self.nr_live_init()` in __init__."""

    def nr_live_init(self) -> None:
        from nrhdr_core.realtime import FrameTimes
        self.set_qos_enabled(True)
        self._nr_times = FrameTimes()
        self._nr_t0 = None
        self._nr_jit_seen = 0
        self._nr_in = self._nr_out = 0
        # the probes hold the element weakly: a bound method would keep it alive through its own pads
        ref = weakref.ref(self)

        def probe(name):
            def call(pad, info):
                el = ref()
                return getattr(el, name)(pad, info) if el is not None else Gst.PadProbeReturn.OK
            return call

        self.sinkpad.add_probe(Gst.PadProbeType.BUFFER, probe("_nr_sink_probe"))
        self.srcpad.add_probe(Gst.PadProbeType.BUFFER, probe("_nr_src_probe"))

    def _nr_fixed_latency(self) -> float:
        return self.settings.processing_latency

    def nr_property_changed(self, name, value) -> None:
        if name == LATENCY_PROP.name:
            self.post_message(Gst.Message.new_latency(self))

    def _nr_sink_probe(self, pad, info):
        from nrhdr_core.realtime import JitWatch
        self._nr_in += 1
        self._nr_jit_seen = JitWatch.count
        self._nr_t0 = time.perf_counter()
        return Gst.PadProbeReturn.OK

    def _nr_src_probe(self, pad, info):
        t0, self._nr_t0 = self._nr_t0, None
        self._nr_out += 1
        if t0 is not None and self._nr_times.add(time.perf_counter() - t0) and self._nr_fixed_latency() < 0:
            self.post_message(Gst.Message.new_latency(self))
        from nrhdr_core.realtime import JitWatch
        if t0 is not None and JitWatch.count != self._nr_jit_seen:  # compiled inside this frame's transform
            self._nr_report_jit("while streaming", self._nr_jit_seen)
        return Gst.PadProbeReturn.OK

    def _nr_report_jit(self, when, seen):
        from nrhdr_core.realtime import JitWatch
        n, sec, names = JitWatch.since((seen, JitWatch.seconds))
        text = (f"{self.get_name()}: numba compiled {n} function(s) {when} (not in the numba cache: run "
                f"'nrhdr warmup' once after install or after a source change)"
                + (f": {', '.join(names)}" if names else ""))
        Gst.info(text)
        self.message_full(Gst.MessageType.INFO, Gst.core_error_quark(), int(Gst.CoreError.FAILED), text,
                          text, __file__, "nr_live", 0)  # gst-launch prints an INFO's debug text only

    def nr_live_reset(self) -> None:
        self._nr_times.reset()
        self._nr_in = self._nr_out = 0

    def nr_qos_skipped(self) -> int:
        """Buffers that entered and were not pushed (dropped by QoS), the one in flight excluded."""
        return max(self._nr_in - self._nr_out - (1 if self._nr_t0 is not None else 0), 0)

    def nr_processing_latency(self) -> int:
        """Nanoseconds this element adds to the pipeline latency."""
        ms = self._nr_fixed_latency()
        sec = ms / 1e3 if ms >= 0 else self._nr_times.estimate()
        return int(sec * Gst.SECOND)

    def nr_live_query(self, direction, query):
        ok = GstBase.BaseTransform.do_query(self, direction, query)
        if ok and query.type == Gst.QueryType.LATENCY and direction == Gst.PadDirection.SRC:
            live, lo, hi = query.parse_latency()
            own = self.nr_processing_latency()
            query.set_latency(live, lo + own, hi if hi == Gst.CLOCK_TIME_NONE else hi + own)
        return ok

    def nr_warmup(self, fn, *args, **kw):
        """Call a core warm-up; report numba compilations it caused (a cache miss: `nrhdr warmup`)."""
        from nrhdr_core.realtime import JitWatch
        snap = JitWatch.snapshot()
        t0 = time.perf_counter()
        out = fn(*args, **kw)
        if JitWatch.count != snap[0]:
            self._nr_report_jit(f"at start in {time.perf_counter() - t0:.1f} s", snap[0])
        return out
