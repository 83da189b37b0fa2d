"""nrcrosstalk: crosstalk correction of HDR frames in place (paper section 3.2).

Applies the camera profile's crosstalk calibration with `nrhdr_core.crosstalk.correct(values, state,
profile, mode)` on the mapped frame. Without a calibration in the profile (or with mode=off) the core
returns the frame unchanged, so frames pass through untouched. Mosaic frames of a colour sensor (caps `cfa`)
pass with their cfa, which must be the profile's; colour frames are refused by name.
"""
from __future__ import annotations

import os
import time

from nrhdr_core.crosstalk import LUT_FORMS, MODES

from ._common import (LATENCY_PROP, Gst, GstBase, HdrInfo, LiveTiming, NrElement, Prop, PropertyTable,
                      check_hdr_buffer, debug_category, guarded, hdr_transform_templates, load_profile, map_hdr,
                      starting)
from ._profiles import ALLOW_OUTSIDE_PROP

PROPERTIES = PropertyTable("GstNrCrosstalk", [
    Prop("profile", str, "", "Camera profile",
         "Camera profile JSON with the crosstalk calibration. Empty = the profile named in the caps by "
         "nrvalidity (field 'profile')"),
    ALLOW_OUTSIDE_PROP,
    Prop("mode", MODES, "kernel", "Correction mode",
         "'kernel' = each pixel's calibrated neighbour kernel applied to its actual neighbours (accurate, "
         "slower: docs/CROSSTALK.md); 'lut' = the paper's per-code look-up table (fast, assumes neighbours as "
         "bright as the pixel); 'off' = pass frames through. Without a calibration in the profile every mode "
         "passes frames through", playing=True),
    Prop("lut", LUT_FORMS, "compact", "LUT form",
         "mode=lut: 'compact' = each pixel's curve resampled at 14 codes (derived from the calibration when "
         "the element starts; ~3x less time at 1080p, median error 0.06 % against the full table, "
         "docs/CROSSTALK.md 'Compact LUT'); 'full' = the calibration's per-pixel table, every knot",
         playing=True),
    LATENCY_PROP,
])


class NrCrosstalk(NrElement, LiveTiming, GstBase.BaseTransform):
    __gtype_name__ = "GstNrCrosstalk"
    PROPERTIES = PROPERTIES
    DEBUG_CATEGORY = debug_category("nrcrosstalk", "nrhdr crosstalk correction")
    __gstmetadata__ = (
        "nrhdr crosstalk correction",
        "Filter/Effect/Video",
        "Corrects optical/electrical crosstalk between ND-filtered and regular pixels of HDR frames "
        "(other/x-nrhdr) with the camera profile's calibration (paper 3.2); identity without a calibration",
        "nrhdr project",
    )
    __gsttemplates__ = hdr_transform_templates()

    do_gst_base_transform_query = LiveTiming.nr_live_query

    def __init__(self):
        super().__init__()
        self.nr_live_init()
        self._profile = None
        self._info = None
        self._calibrated = False
        self._frames = 0
        self.set_in_place(True)
        self.set_passthrough(False)

    @starting
    def do_start(self):
        self._profile = None
        if self.settings.profile:
            try:
                self._profile = load_profile(self.settings.profile, self.settings.allow_outside_paths)
            except ValueError as e:
                self.post_error(str(e), kind="read")
                return False
        from nrhdr_core import chain
        s = self.settings
        if s.mode != "off":
            cfa = self._profile.cfa if self._profile is not None else "none"
            self.nr_warmup(chain.warmup, chain.ChainSettings(crosstalk=s.mode, crosstalk_lut=s.lut),
                           stages=("crosstalk",), elements=True, cfa=cfa)
        self._frames = 0
        return True

    def do_stop(self):
        self._info = None
        return True

    @guarded("set_caps", False)
    def do_set_caps(self, incaps, outcaps):
        info = HdrInfo.from_caps(incaps, element="nrcrosstalk")
        if not self.settings.profile:
            if not info.profile:
                self.post_error("no camera profile: set the 'profile' property or put nrvalidity "
                                "upstream (its caps name the profile)", kind="settings")
                return False
            try:
                self._profile = load_profile(info.profile, from_caps=True)
            except ValueError as e:
                self.post_error(str(e), kind="read")
                return False
        p = self._profile
        if not self._check_same_sensor(p, info):
            return False
        if p.cfa != info.cfa:
            self.post_error(f"profile {p.path} has cfa {p.cfa} but the stream's caps say cfa={info.cfa}: set the "
                            f"'profile' property to a profile of the camera that recorded the stream",
                            kind="settings")
            return False
        if (p.width, p.height) != (info.width, info.height):
            self.post_error(f"profile {p.path} has a {p.width}x{p.height} mask but the stream is "
                            f"{info.width}x{info.height}", kind="format")
            return False
        self._info = info
        self._calibrated = p.crosstalk is not None
        s = self.settings
        if self._calibrated and s.mode == "lut" and s.lut == "compact":
            from nrhdr_core import crosstalk
            t0 = time.perf_counter()
            crosstalk.compact_for(p)       # derived once per profile, not in the first frame
            self.gst_debug(f"compact LUT ready in {time.perf_counter() - t0:.2f} s")
        self.gst_debug(f"caps {incaps.to_string()}; profile {p.path}"
                       f"{'' if self._calibrated else ' has no crosstalk calibration: frames pass unchanged'}")
        return True

    def _check_same_sensor(self, p, info) -> bool:
        """A calibration must belong to the sensor that recorded the stream (the profile nrvalidity named in
        the caps): same mask size, pattern and bit depth, else an element error naming both files."""
        if p.crosstalk is None or not self.settings.profile or not info.profile:
            return True
        if p.path is not None and os.path.abspath(info.profile) == os.path.abspath(str(p.path)):
            return True
        from nrhdr_core import profile as profile_mod
        try:
            profile_mod.check_same_sensor(p, load_profile(info.profile, from_caps=True))
        except ValueError as e:
            self.post_error(str(e), kind="settings")
            return False
        return True

    @guarded(lambda self: f"frame {self._frames}", Gst.FlowReturn.ERROR)
    def do_transform_ip(self, buf):
        s = self.settings
        if self._info is None:
            self.post_error("no caps negotiated before the first buffer", kind="negotiation")
            return Gst.FlowReturn.NOT_NEGOTIATED
        if s.mode != "off":       # (without a calibration the core returns the frame unchanged)
            from nrhdr_core import crosstalk
            t0 = time.perf_counter()
            with self.warnings_to_bus(), map_hdr(buf, self._info, write=True) as (values, state):
                v2, s2 = crosstalk.correct(values, state, self._profile, s.mode, lut=s.lut)
                copied = v2 is not values or s2 is not state
                if v2 is not values:
                    values[...] = v2
                if s2 is not state:
                    state[...] = s2
            if self.gst_debug_enabled(Gst.DebugLevel.LOG):
                what = f"mode={s.mode} lut={s.lut}" if self._calibrated else "unchanged (no calibration)"
                self.gst_log(f"frame {self._frames} pts {Gst.TIME_ARGS(buf.pts)}: {what} in "
                             f"{(time.perf_counter() - t0) * 1e3:.2f} ms"
                             f"{' (result copied back: core returned new arrays)' if copied else ''}")
        else:
            check_hdr_buffer(buf, self._info)
            if self.gst_debug_enabled(Gst.DebugLevel.LOG):
                self.gst_log(f"frame {self._frames} pts {Gst.TIME_ARGS(buf.pts)}: skipped (mode=off)")
        self._frames += 1
        return Gst.FlowReturn.OK
