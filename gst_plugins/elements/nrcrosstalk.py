"""nrcrosstalk: crosstalk correction of HDR frames in place (paper section 3.2).

Applies the camera profile's crosstalk calibration with `nrhdr_core.crosstalk.correct(values, state,
profile, mode)` on the mapped frame. Without a calibration in the profile (or with mode=off) the core
returns the frame unchanged, so frames pass through untouched.
"""
from __future__ import annotations

import time

from ._common import LiveTiming, live_latency_property  # live operation: QoS, latency (issue #7)
from ._common import (MUTABLE_PLAYING, MUTABLE_READY, Choice, ErrorPoster, GObject, Gst, GstBase, HdrInfo,
                      debug_category, hdr_template_caps, load_profile, map_hdr)

MODES = ("lut", "kernel", "off")
LUT_FORMS = ("compact", "full")   # = nrhdr_core.crosstalk.LUT_FORMS (not imported here: keeps import light)


class NrCrosstalk(ErrorPoster, LiveTiming, GstBase.BaseTransform):
    __gtype_name__ = "GstNrCrosstalk"
    DEBUG_CATEGORY = debug_category("nrcrosstalk", "nrhdr crosstalk correction")
    __gstmetadata__ = (
        "nrhdr crosstalk correction",
        "Filter/Effect/Video",
        "Corrects optical/electrical crosstalk between ND-filtered and regular pixels of HDR frames "
        "(other/x-nrhdr) with the camera profile's calibration (paper 3.2); identity without a calibration",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, hdr_template_caps()),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, hdr_template_caps()),
    )

    do_gst_base_transform_query = LiveTiming.nr_live_query
    processing_latency = live_latency_property()

    def __init__(self):
        super().__init__()
        self.nr_live_init()
        self._profile_path = ""
        self._mode = Choice("mode", MODES, "kernel")
        self._lut = Choice("lut", LUT_FORMS, "compact")
        self._profile = None
        self._info = None
        self._calibrated = False
        self._frames = 0
        self.set_in_place(True)
        self.set_passthrough(False)

    @GObject.Property(type=str, default="", nick="Camera profile",
                      blurb="Camera profile JSON with the crosstalk calibration. Empty = the profile named "
                            "in the caps by nrvalidity (field 'profile')",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_READY)
    def profile(self):
        return self._profile_path

    @profile.setter
    def profile(self, value):
        self._profile_path = value or ""

    @GObject.Property(type=str, default="kernel", nick="Correction mode",
                      blurb="'kernel' = each pixel's calibrated neighbour kernel applied to its actual "
                            "neighbours (accurate, slower: docs/CROSSTALK.md); 'lut' = the paper's "
                            "per-code look-up table (fast, assumes neighbours as bright as the pixel); "
                            "'off' = pass frames through "
                            "(one of: kernel, lut, off). Without a calibration in the profile every mode "
                            "passes frames through",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING)
    def mode(self):
        return self._mode.value

    @mode.setter
    def mode(self, value):
        self.set_choice(self._mode, value)

    @GObject.Property(type=str, default="compact", nick="LUT form",
                      blurb="mode=lut: 'compact' = each pixel's curve resampled at 14 codes (derived from the "
                            "calibration when the element starts; fast: ~3x less time at 1080p, median error "
                            "0.06 % against the full table, docs/CROSSTALK.md 'Compact LUT'); 'full' = the "
                            "calibration's per-pixel table, every knot (accurate) (one of: compact, full)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING)
    def lut(self):
        return self._lut.value

    @lut.setter
    def lut(self, value):
        self.set_choice(self._lut, value)

    def do_start(self):
        self.reset_errors()
        try:
            for c in (self._mode, self._lut):
                if c.invalid:
                    self.post_error(c.invalid, kind="settings")
                    return False
            self._profile = None
            if self._profile_path:
                try:
                    self._profile = load_profile(self._profile_path)
                except ValueError as e:
                    self.post_error(str(e), kind="read")
                    return False
            from nrhdr_core import crosstalk
            if hasattr(crosstalk, "warmup"):
                self.nr_warmup(crosstalk.warmup)
            self._frames = 0
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("start", e)
            return False

    def do_stop(self):
        self._info = None
        return True

    def do_set_caps(self, incaps, outcaps):
        try:
            info = HdrInfo.from_caps(incaps)
            if not self._profile_path:
                if not info.profile:
                    self.post_error("no camera profile: set the 'profile' property or put nrvalidity "
                                    "upstream (its caps name the profile)", kind="settings")
                    return False
                try:
                    self._profile = load_profile(info.profile)
                except ValueError as e:
                    self.post_error(str(e), kind="read")
                    return False
            p = self._profile
            if not self._check_same_sensor(p, info):
                return False
            if (p.width, p.height) != (info.width, info.height):
                self.post_error(f"profile {p.path} has a {p.width}x{p.height} mask but the stream is "
                                f"{info.width}x{info.height}", kind="format")
                return False
            self._info = info
            calibrated = getattr(self._profile, "crosstalk", None) is not None
            self._calibrated = calibrated
            if calibrated and self._mode.value == "lut" and self._lut.value == "compact":
                from nrhdr_core import crosstalk
                t0 = time.perf_counter()
                crosstalk.compact_for(p)       # derived once per profile, not in the first frame
                self.gst_debug(f"compact LUT ready in {time.perf_counter() - t0:.2f} s")
            self.gst_debug(f"caps {incaps.to_string()}; profile {self._profile.path}"
                           f"{'' if calibrated else ' has no crosstalk calibration: frames pass unchanged'}")
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("set_caps", e)
            return False

    def _check_same_sensor(self, p, info) -> bool:
        """Issue 9: a calibration must belong to the sensor that recorded the stream (the profile nrvalidity
        named in the caps): same mask size, pattern and bit depth, else an element error naming both files."""
        if p.crosstalk is None or not self._profile_path or not info.profile:
            return True
        import os
        if p.path is not None and os.path.abspath(info.profile) == os.path.abspath(str(p.path)):
            return True
        from nrhdr_core import profile as profile_mod
        try:
            profile_mod.check_same_sensor(p, load_profile(info.profile))
        except ValueError as e:
            self.post_error(str(e), kind="settings")
            return False
        return True

    def do_transform_ip(self, buf):
        try:
            mode = self._mode.value
            if self._info is None:
                self.post_error("no caps negotiated before the first buffer", kind="negotiation")
                return Gst.FlowReturn.NOT_NEGOTIATED
            if mode != "off":       # (without a calibration the core returns the frame unchanged)
                from nrhdr_core import crosstalk
                t0 = time.perf_counter()
                with self.warnings_to_bus(), map_hdr(buf, self._info, write=True) as (values, state):
                    v2, s2 = crosstalk.correct(values, state, self._profile, mode, lut=self._lut.value)
                    copied = v2 is not values or s2 is not state
                    if v2 is not values:
                        values[...] = v2
                    if s2 is not state:
                        state[...] = s2
                if self.gst_debug_enabled(Gst.DebugLevel.LOG):
                    self.gst_log(f"frame {self._frames} pts {Gst.TIME_ARGS(buf.pts)}: "
                                 f"{f'mode={mode} lut={self._lut.value}' if self._calibrated else 'unchanged (no calibration)'} in "
                                 f"{(time.perf_counter() - t0) * 1e3:.2f} ms"
                                 f"{' (result copied back: core returned new arrays)' if copied else ''}")
            elif self.gst_debug_enabled(Gst.DebugLevel.LOG):
                self.gst_log(f"frame {self._frames} pts {Gst.TIME_ARGS(buf.pts)}: skipped (mode=off)")
            self._frames += 1
            return Gst.FlowReturn.OK
        except Exception as e:  # noqa: BLE001
            return self.post_exception(f"frame {self._frames}", e)
