"""nrreconstruct: fills the missing pixels of HDR frames in place (paper 2.2, 2.4, 5).

`nrhdr_core.reconstruction.reconstruct(values, known, method, preset, lower, upper)` on the mapped frame;
known = reason VALID; clipped pixels' values are lower bounds and too-dark pixels' upper bounds
(`use-bounds`). Filled pixels get the RECONSTRUCTED bit (their reason is kept). `method` and `preset` can
change while PLAYING: the setter swaps an immutable parameter object that the streaming thread reads once
per frame. Posts an element message "nrhdr-frame-stats" per frame.
"""
from __future__ import annotations

import dataclasses
import time

from ._common import (MUTABLE_PLAYING, Choice, ErrorPoster, GObject, Gst, GstBase, HdrInfo,
                      hdr_template_caps, map_hdr, np)

METHODS = ("fse", "linear", "nearest", "preview")
PRESETS = ("preview", "fast", "balanced", "best")
STATS_MESSAGE = "nrhdr-frame-stats"


@dataclasses.dataclass(frozen=True)
class ReconParams:
    method: str = "fse"
    preset: str = "balanced"
    use_bounds: bool = True


class NrReconstruct(ErrorPoster, GstBase.BaseTransform):
    __gtype_name__ = "GstNrReconstruct"
    __gstmetadata__ = (
        "nrhdr missing-pixel reconstruction",
        "Filter/Effect/Video",
        "Fills the missing (clipped, too dark, discarded) pixels of HDR frames (other/x-nrhdr) by "
        "Frequency Selective Extrapolation, linear (Delaunay) or nearest interpolation, or a fast "
        "pull-push preview; posts 'nrhdr-frame-stats' element messages",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, hdr_template_caps()),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, hdr_template_caps()),
    )

    def __init__(self):
        super().__init__()
        self._params = ReconParams()
        self._method = Choice("method", METHODS, "fse")
        self._preset = Choice("preset", PRESETS, "balanced")
        self._post_stats = True
        self._info = None
        self._frames = 0
        self.set_in_place(True)
        self.set_passthrough(False)

    # ---- properties (method/preset/use-bounds mutable while PLAYING) ---------------------------------
    @GObject.Property(type=str, default="fse", nick="Method",
                      blurb="Reconstruction method: 'fse' = Frequency Selective Extrapolation (paper, best), "
                            "'linear' = Delaunay-linear, 'nearest' = nearest known pixel, 'preview' = fast "
                            "pull-push for live preview (one of: fse, linear, nearest, preview). "
                            "Changeable while PLAYING",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING)
    def method(self):
        return self._params.method

    @method.setter
    def method(self, value):
        v = self.set_choice(self._method, value)
        if v is not None:
            self._params = dataclasses.replace(self._params, method=v)

    @GObject.Property(type=str, default="balanced", nick="Preset",
                      blurb="FSE parameter preset, speed against quality (one of: preview, fast, balanced, "
                            "best); ignored by other methods. Changeable while PLAYING",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING)
    def preset(self):
        return self._params.preset

    @preset.setter
    def preset(self, value):
        v = self.set_choice(self._preset, value)
        if v is not None:
            self._params = dataclasses.replace(self._params, preset=v)

    @GObject.Property(type=bool, default=True, nick="Use bounds",
                      blurb="Keep reconstructed clipped pixels at or above their clip level and too-dark "
                            "pixels at or below l_min x ND (the bounds their state implies)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING)
    def use_bounds(self):
        return self._params.use_bounds

    @use_bounds.setter
    def use_bounds(self, value):
        self._params = dataclasses.replace(self._params, use_bounds=bool(value))

    @GObject.Property(type=bool, default=True, nick="Post statistics",
                      blurb="Post an element message 'nrhdr-frame-stats' per frame (fields frame, missing "
                            "= fraction of pixels reconstructed, method, seconds)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING)
    def post_stats(self):
        return self._post_stats

    @post_stats.setter
    def post_stats(self, value):
        self._post_stats = bool(value)

    # ---- state --------------------------------------------------------------------------------------
    def do_start(self):
        self.reset_errors()
        try:
            for c in (self._method, self._preset):
                if c.invalid:
                    self.post_error(c.invalid, kind="settings")
                    return False
            from nrhdr_core import reconstruction
            reconstruction.warmup(self._params.method)  # others compile on first use after a switch
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
            self._info = HdrInfo.from_caps(incaps)
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("set_caps", e)
            return False

    # ---- data ---------------------------------------------------------------------------------------
    def do_transform_ip(self, buf):
        p = self._params  # one read per frame: a consistent parameter set
        try:
            if self._info is None:
                self.post_error("no caps negotiated before the first buffer", kind="negotiation")
                return Gst.FlowReturn.NOT_NEGOTIATED
            from nrhdr_core import reconstruction
            t0 = time.perf_counter()
            with map_hdr(buf, self._info, write=True) as (values, state):
                # one fused pass for known mask + bounds, in place, measured pixels untouched (perf, #7)
                n_miss = reconstruction.reconstruct_frame(values, state, method=p.method, preset=p.preset,
                                                          use_bounds=p.use_bounds)
            dt = time.perf_counter() - t0
            if self._post_stats:
                self._post_frame_stats(n_miss / float(self._info.pixels), p.method, dt)
            self._frames += 1
            return Gst.FlowReturn.OK
        except Exception as e:  # noqa: BLE001
            return self.post_exception(f"frame {self._frames} (method={p.method}, preset={p.preset})", e)

    def _post_frame_stats(self, missing: float, method: str, seconds: float) -> None:
        s = Gst.Structure.new_empty(STATS_MESSAGE)
        s.set_value("frame", GObject.Value(GObject.TYPE_UINT64, self._frames))
        s.set_value("missing", GObject.Value(GObject.TYPE_DOUBLE, float(missing)))
        s.set_value("method", method)
        s.set_value("seconds", GObject.Value(GObject.TYPE_DOUBLE, float(seconds)))
        self.post_message(Gst.Message.new_element(self, s))
