"""nrvalidity: raw GRAY16_LE sensor frames in, HDR frames (`other/x-nrhdr`) out (paper section 2.3, Eq. 3).

Clipped pixels and attenuated pixels below l_min become missing, attenuated pixels are scaled by ND, and a
per-pixel state byte (valid / clipped / too dark / discarded, + attenuated bit) travels after the float
plane in the frame's one block (docs/ARCHITECTURE.md). Core: `nrhdr_core.validity.classify`, writing straight
into the mapped output frame, which comes from a buffer pool (allocated once per size).

Caps follow the profile: once the profile is known, the sink pad advertises only the mask's width and
height upstream (so `videotestsrc ! video/x-raw,format=GRAY16_LE ! nrvalidity profile=...` or `videoscale !
nrvalidity` negotiate that size); pixel-aspect-ratio and interlace-mode pass through.
"""
from __future__ import annotations

import os
import time
import urllib.parse

from ._common import LiveTiming, live_latency_property  # live operation: QoS, latency (issue #7)
from ._common import (CONTROLLABLE, HDR_LAYOUT, HDR_MEDIA_TYPE, MUTABLE_PLAYING, MUTABLE_READY, Choice,
                      ErrorPoster, GObject, Gst, GstBase, GstVideo, HdrInfo, HdrPool, copy_fields,
                      copy_timestamps, debug_category, hdr_template_caps, load_profile, map_hdr, map_video,
                      raw_template_caps, transform_caps_by_structure)

MODES = ("all", "best", "threshold")


class NrValidity(ErrorPoster, LiveTiming, GstBase.BaseTransform):
    __gtype_name__ = "GstNrValidity"
    DEBUG_CATEGORY = debug_category("nrvalidity", "nrhdr validity and ND scaling")
    __gstmetadata__ = (
        "nrhdr validity and ND scaling",
        "Filter/Converter/Video",
        "Raw GRAY16_LE frames of a non-regular ND sensor to linear HDR frames (other/x-nrhdr): clipped and "
        "too-dark pixels become missing, attenuated pixels are scaled by ND (paper Eq. 3), a per-pixel "
        "state travels with the frame",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS,
                            raw_template_caps("GRAY16_LE")),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS,
                            hdr_template_caps(strict=True)),
    )

    do_gst_base_transform_query = LiveTiming.nr_live_query
    processing_latency = live_latency_property()

    def __init__(self):
        super().__init__()
        self._pool = None
        self.nr_live_init()
        self._profile_path = ""
        self._mode = Choice("mode", MODES, "threshold")
        self._params = ("threshold", -1.0)   # (mode, l_min): swapped whole, read once per frame
        self._dark_policy = Choice("dark-policy", ("threshold", "weighted"), "weighted")  # issue 8
        self._profile = None
        self._in_info = None
        self._out_info = None
        self._frames = 0
        self._size_checked = False
        self.set_passthrough(False)
        self.set_in_place(False)

    # ---- properties ---------------------------------------------------------------------------------
    @GObject.Property(type=str, default="", nick="Camera profile",
                      blurb="Camera profile JSON (nrhdr_core.profile): ND mask, ND factor, clip code, black "
                            "level, l_min. Required; the stream's frame size must equal the mask's",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_READY)
    def profile(self):
        return self._profile_path

    @profile.setter
    def profile(self, value):
        self._profile_path = value or ""

    @GObject.Property(type=str, default="threshold", nick="Selection mode",
                      blurb="Pixel selection (paper 2.3): 'all' = every pixel neither clipped nor below "
                            "SNR 0 dB; 'best' = attenuated pixels dropped where a valid regular neighbour "
                            "exists; 'threshold' = attenuated pixels below l-min are invalid "
                            "(one of: all, best, threshold)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING)
    def mode(self):
        return self._params[0]

    @mode.setter
    def mode(self, value):
        v = self.set_choice(self._mode, value)
        if v is not None:
            self._params = (v, self._params[1])

    @GObject.Property(type=float, default=-1.0, minimum=-1.0, maximum=65535.0, nick="l_min",
                      blurb="Threshold mode: attenuated pixels whose signal (code - black level) is below "
                            "this are too dark (paper 2.3). -1 = the profile's l_min",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING | CONTROLLABLE)
    def l_min(self):
        return self._params[1]

    @l_min.setter
    def l_min(self, value):
        self._params = (self._params[0], float(value))

    # ---- dark policy (issue 8, helper "hdr") --------------------------------------------------------
    @GObject.Property(type=str, default="weighted", nick="Dark policy",
                      blurb="Threshold mode: 'threshold' = attenuated pixels below l-min are missing with "
                            "l-min x ND as upper bound (paper 2.3); 'weighted' = between SNR 0 dB and "
                            "4 x l-min they are kept as NOISY measurements that nrreconstruct fuses with its "
                            "estimate by their noise (measured better, docs/BENCHMARKS.md) "
                            "(one of: threshold, weighted)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_PLAYING)
    def dark_policy(self):
        return self._dark_policy.value

    @dark_policy.setter
    def dark_policy(self, value):
        self.set_choice(self._dark_policy, value)

    # ---- state --------------------------------------------------------------------------------------
    def do_start(self):
        self.reset_errors()
        try:
            for c in (self._mode, self._dark_policy):
                if c.invalid:
                    self.post_error(c.invalid, kind="settings")
                    return False
            try:
                self._profile = load_profile(self._profile_path)
            except ValueError as e:  # ProfileError is a ValueError
                self.post_error(str(e), kind="settings" if not self._profile_path else "read")
                return False
            from nrhdr_core import validity
            self.nr_warmup(validity.warmup)
            self._frames = 0
            self._size_checked = False
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("start", e)
            return False

    def do_stop(self):
        self._profile = None
        self._in_info = self._out_info = None
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        return True

    # ---- caps ---------------------------------------------------------------------------------------
    def _known_profile(self):
        """The loaded profile, or (before start, e.g. caps queries while linking) the one the property
        names if it loads; None when unknown. Errors are reported by do_start, not here."""
        if self._profile is not None:
            return self._profile
        if not self._profile_path:
            return None
        try:
            return load_profile(self._profile_path)
        except Exception:  # noqa: BLE001
            return None

    def do_transform_caps(self, direction, caps, filt):
        prof = self._known_profile()

        def to_hdr(s):
            n = Gst.Structure.new_empty(HDR_MEDIA_TYPE)
            n.set_value("layout", HDR_LAYOUT)
            copy_fields(s, n)
            if prof is not None:
                n.set_value("white", float(prof.white))
                n.set_value("diffuse-white", float(prof.regular_white))
                if prof.path is not None:
                    n.set_value("profile", str(prof.path))
            return [n]

        def to_raw(s):
            n = Gst.Structure.new_empty("video/x-raw")
            n.set_value("format", "GRAY16_LE")
            copy_fields(s, n)
            return [n]

        sink = direction == Gst.PadDirection.SINK
        out = transform_caps_by_structure(caps, None, to_hdr if sink else to_raw, self)
        if prof is not None:  # the mask's size only, both ways (empty caps if the other side cannot have it)
            media = HDR_MEDIA_TYPE if sink else "video/x-raw"
            out = out.intersect(Gst.Caps.from_string(f"{media}, width=(int){prof.width}, "
                                                     f"height=(int){prof.height}"))
        if filt is not None:
            out = filt.intersect_full(out, Gst.CapsIntersectMode.FIRST)
        self.gst_log(f"transform_caps {direction.value_nick}: {caps.to_string()} -> {out.to_string()}")
        return out

    def do_accept_caps(self, direction, caps):
        ok = GstBase.BaseTransform.do_accept_caps(self, direction, caps)
        try:
            self._explain_refused_caps(ok, direction, caps)
        except Exception:  # noqa: BLE001 - only an explanation; the answer stands
            pass
        return ok

    def _explain_refused_caps(self, ok, direction, caps):
        """A caps event nrvalidity refuses (e.g. GRAY8 from rawvideoparse format=gray8) would only give
        upstream's 'not-negotiated': say what is wrong, once."""
        if not ok and direction == Gst.PadDirection.SINK and caps is not None and caps.is_fixed():
            s = caps.get_structure(0)
            fmt = s.get_string("format") if s.has_field("format") else None
            prof = self._known_profile()
            okw, w = s.get_int("width")
            okh, h = s.get_int("height")
            if (s.get_name() == "video/x-raw" and fmt == "GRAY16_LE" and prof is not None and okw and okh
                    and (w, h) != (prof.width, prof.height)):
                self.post_error(self._size_mismatch(prof, w, h), kind="format")
            elif s.get_name() == "video/x-raw" and fmt and fmt != "GRAY16_LE":
                okw, w = s.get_int("width")
                okh, h = s.get_int("height")
                size = f" {w}x{h}" if okw and okh else ""
                self.post_error(f"needs raw GRAY16_LE sensor frames (video/x-raw, format=GRAY16_LE), got "
                                f"{fmt}{size}", kind="format")
            else:
                self.post_error(f"cannot accept {caps.to_string()}: needs video/x-raw, format=GRAY16_LE",
                                kind="format")
        return ok

    def do_set_caps(self, incaps, outcaps):
        try:
            vi = GstVideo.VideoInfo.new_from_caps(incaps)
            if vi is None:
                self.post_error(f"cannot parse input caps {incaps.to_string()}", kind="format")
                return False
            prof = self._profile
            if prof is None:
                self.post_error("no camera profile loaded", kind="settings")
                return False
            if (vi.width, vi.height) != (prof.width, prof.height):
                self.post_error(self._size_mismatch(prof, vi.width, vi.height), kind="format")
                return False
            self._in_info = vi
            self._out_info = HdrInfo.from_caps(outcaps)
            self._pool = HdrPool.for_info(self._pool, self._out_info)
            self.gst_debug(f"caps: {incaps.to_string()} -> {outcaps.to_string()}; pool of "
                           f"{self._out_info.size}-byte frames")
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("set_caps", e)
            return False

    def _size_mismatch(self, prof, w, h) -> str:
        name = os.path.basename(str(prof.path)) if prof.path else self._profile_path
        return f"profile {name} has a {prof.width}x{prof.height} mask but the stream is {w}x{h}"

    # ---- data ---------------------------------------------------------------------------------------
    def do_prepare_output_buffer(self, inbuf):
        try:
            oi = self._out_info
            if oi is None or self._pool is None:
                self.post_error("no caps negotiated before the first buffer", kind="negotiation")
                return Gst.FlowReturn.NOT_NEGOTIATED, None
            out = self._pool.acquire()
            copy_timestamps(inbuf, out)
            return Gst.FlowReturn.OK, out
        except Exception as e:  # noqa: BLE001
            return self.post_exception("prepare_output_buffer", e), None

    def _raw_parser_upstream(self) -> bool:
        """True when the frames come (through queues/capsfilters only) from rawvideoparse/videoparse, so
        the upstream byte size is the raw file's and our buffer size its frame size."""
        pad = self.sinkpad.get_peer()
        for _ in range(16):
            el = pad.get_parent_element() if pad is not None else None
            f = el.get_factory() if el is not None else None
            name = f.get_name() if f is not None else ""
            if name in ("rawvideoparse", "videoparse"):
                return True
            if name not in ("queue", "queue2", "capsfilter", "identity") or len(el.sinkpads) != 1:
                return False
            pad = el.sinkpads[0].get_peer()
        return False

    def _check_truncated(self, inbuf) -> bool:
        """rawvideoparse silently drops a partial last frame: ask upstream for the byte size of its input
        (filesrc answers) and refuse a file that is not a whole number of frames."""
        self._size_checked = True
        if not self._check_stride(inbuf):
            return False
        frame = inbuf.get_size()
        try:
            if not self._raw_parser_upstream():
                return True
            ok, total = self.sinkpad.peer_query_duration(Gst.Format.BYTES)
        except Exception:  # noqa: BLE001
            return True
        if not ok or total is None or total <= 0 or frame <= 0:
            return True
        if not self._check_stride(inbuf, total):
            return False
        if total % frame == 0:
            return True
        where = "input"
        try:
            q = Gst.Query.new_uri()
            if self.sinkpad.peer_query(q):
                uri = q.parse_uri()
                if uri and uri.startswith("file://"):
                    where = urllib.parse.unquote(uri[len("file://"):])
                elif uri:
                    where = uri
        except Exception:  # noqa: BLE001
            pass
        vi = self._in_info
        self.post_error(f"{where} is {total} bytes, not a whole number of {frame}-byte {vi.width}x{vi.height} "
                        f"GRAY16_LE frames ({total // frame} frames + {total % frame} bytes): the last frame "
                        f"is truncated", kind="format")
        return False

    def _input_name(self) -> str:
        try:
            q = Gst.Query.new_uri()
            if self.sinkpad.peer_query(q):
                uri = q.parse_uri()
                if uri and uri.startswith("file://"):
                    return urllib.parse.unquote(uri[len("file://"):])
                return uri or "input"
        except Exception:  # noqa: BLE001
            pass
        return "input"

    def _check_stride(self, inbuf, total=None) -> bool:
        """Issue 9: a stride that does not match the frame. GStreamer pads GRAY16_LE rows of odd width to 4
        bytes; a raw file of unpadded rows (what nrhdr writes) parsed without plane-strides gives garbage
        (or a misleading 'truncated' error). Detected from the file size (a whole number of unpadded frames
        while the rows are padded) or a GstVideoMeta whose stride differs from the caps'."""
        vi = self._in_info
        w, h = vi.width, vi.height
        tight, stride = 2 * w * h, int(vi.stride[0])
        meta_stride = None
        try:
            meta = GstVideo.buffer_get_video_meta(inbuf)
            if meta is not None:
                meta_stride = int(meta.stride[0])
        except Exception:  # noqa: BLE001 - no usable meta: size checks only
            meta_stride = None
        size = inbuf.get_size()
        if size != vi.size and (size % h or size // h < 2 * w):
            self.post_error(f"{self._input_name()}: a buffer of {size} bytes is not {h} whole rows of a {w}x{h} "
                            f"GRAY16_LE frame ({vi.size} bytes with rows padded to {stride}, {tight} unpadded): "
                            f"wrong size, or set plane-strides=<ROW_BYTES> on rawvideoparse", kind="format")
            return False
        used = stride if size == vi.size else size // h
        if meta_stride is not None and meta_stride != used:
            self.post_error(f"{self._input_name()}: the buffers' video meta says rows of {meta_stride} bytes but "
                            f"{size}-byte {w}x{h} frames give {used}: set plane-strides=<{meta_stride}> on "
                            f"rawvideoparse (or fix the source's stride)", kind="format")
            return False
        if total is not None and used != 2 * w and size == vi.size and total % tight == 0:
            self.post_error(f"{self._input_name()} holds a whole number of unpadded {w}x{h} GRAY16_LE frames "
                            f"({total // tight} x {tight} bytes), but rawvideoparse reads rows padded to "
                            f"{used} bytes (GStreamer's default stride for width {w}): set "
                            f"plane-strides=<{2 * w}> on rawvideoparse", kind="format")
            return False
        return True

    def do_before_transform(self, buf):
        try:
            self.sync_controlled(buf)
        except Exception as e:  # noqa: BLE001
            self.gst_warn(f"controller sync failed: {e}")

    def do_transform(self, inbuf, outbuf):
        try:
            if not self._size_checked and not self._check_truncated(inbuf):
                return Gst.FlowReturn.ERROR
            from nrhdr_core import validity
            mode, lm = self._params
            lm = None if lm < 0 else lm
            t0 = time.perf_counter()
            with self.warnings_to_bus(), map_video(inbuf, self._in_info, "<u2", write=False) as raw, \
                    map_hdr(outbuf, self._out_info, write=True) as (values, state):
                validity.classify(raw, self._profile, mode=mode, l_min=lm, values=values, state=state,
                                  dark_policy=self._dark_policy.value)
            if self.gst_debug_enabled(Gst.DebugLevel.LOG):
                self.gst_log(f"frame {self._frames} pts {Gst.TIME_ARGS(inbuf.pts)}: classified "
                             f"{self._in_info.width}x{self._in_info.height} (mode={mode}, l_min="
                             f"{'profile' if lm is None else lm}) in {(time.perf_counter() - t0) * 1e3:.2f} ms")
            self._frames += 1
            return Gst.FlowReturn.OK
        except Exception as e:  # noqa: BLE001
            return self.post_exception(f"frame {self._frames}", e)
