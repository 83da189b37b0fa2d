"""nrvalidity: raw GRAY16_LE (or 8-bit Bayer) sensor frames in, HDR frames (`other/x-nrhdr`) out (paper
section 2.3, Eq. 3).

Clipped pixels and attenuated pixels below l_min become missing, attenuated pixels are scaled by ND, and a
per-pixel state byte (valid / clipped / too dark / discarded, + attenuated bit) travels after the float
plane in the frame's one block (docs/ARCHITECTURE.md). Core: `nrhdr_core.validity.classify`, writing straight
into the mapped output frame, which comes from a buffer pool (allocated once per size).

Caps follow the profile: once the profile is known, the sink pad advertises only the mask's width and
height upstream (so `videotestsrc ! video/x-raw,format=GRAY16_LE ! nrvalidity profile=...` or `videoscale !
nrvalidity` negotiate that size); pixel-aspect-ratio and interlace-mode pass through.

The profile says what the GRAY16_LE words hold (docs/PROFILE.md "Sensor data"): `bit_depth`-bit codes, LSB- or
MSB-aligned, or a packed bit stream (Mono12Packed, Mono12p, Mono10p: aravissrc labels Mono12Packed GRAY16_LE)
whose buffers hold the packed bytes; a buffer whose size does not fit the profile's format, or codes beyond its
bit depth with `out_of_range` "error", is an element error naming the profile.

A colour profile (`cfa` a Bayer phase) puts `cfa` in the output caps (mosaic frames). `video/x-bayer` caps
(8-bit: the only Bayer caps of GStreamer 1.22, aravissrc and v4l2src) are taken when their format is the
profile's cfa and the profile is 8-bit (`bit_depth` 8); rows of W or of W rounded up to 4 bytes (GStreamer's
Bayer stride). Anything else is an element error naming the caps and the profile field at odds.
"""
from __future__ import annotations

import contextlib
import os
import time
import urllib.parse

import numpy as np

from nrhdr_core.validity import DARK_POLICIES, MODES

from ._common import (BAYER_FORMATS, BAYER_MEDIA_TYPE, HDR_LAYOUT, HDR_MEDIA_TYPE, LATENCY_PROP, FrameSizeError,
                      GstBase, GstVideo, Gst, HdrInfo, HdrPool, LiveTiming, NrElement, Prop, PropertyTable,
                      bayer_template_caps, check_video_buffer, copy_fields, copy_timestamps, debug_category,
                      guarded, hdr_template_caps, load_profile, map_hdr, map_video, raw_template_caps, starting,
                      transform_caps_by_structure)
from ._profiles import ALLOW_OUTSIDE_PROP

PROPERTIES = PropertyTable("GstNrValidity", [
    Prop("profile", str, "", "Camera profile",
         "Camera profile JSON (nrhdr_core.profile): ND mask, ND factor, bit depth, white and black level, "
         "alignment, packing, defect pixels, l_min. Required; the stream's frame size must equal the mask's"),
    ALLOW_OUTSIDE_PROP,
    Prop("mode", MODES, "threshold", "Selection mode",
         "Pixel selection (paper 2.3): 'all' = every pixel neither clipped nor below SNR 0 dB; 'best' = "
         "attenuated pixels dropped where a valid regular neighbour exists; 'threshold' = attenuated pixels "
         "below l-min are invalid", playing=True),
    Prop("l-min", float, -1.0, "l_min",
         "Threshold mode: attenuated pixels whose signal (code - black level) is below this are too dark "
         "(paper 2.3). -1 = the profile's l_min", minimum=-1.0, maximum=65535.0, playing=True,
         controllable=True),
    Prop("dark-policy", DARK_POLICIES, "weighted", "Dark policy",
         "Threshold mode: 'threshold' = attenuated pixels below l-min are missing with l-min x ND as upper "
         "bound (paper 2.3); 'weighted' = between SNR 0 dB and 4 x l-min they are kept as NOISY measurements "
         "that nrreconstruct fuses with its estimate by their noise (docs/BENCHMARKS.md)", playing=True),
    LATENCY_PROP,
])


class NrValidity(NrElement, LiveTiming, GstBase.BaseTransform):
    __gtype_name__ = "GstNrValidity"
    PROPERTIES = PROPERTIES
    DEBUG_CATEGORY = debug_category("nrvalidity", "nrhdr validity and ND scaling")
    __gstmetadata__ = (
        "nrhdr validity and ND scaling",
        "Filter/Converter/Video",
        "Raw GRAY16_LE (or 8-bit Bayer) frames of a non-regular ND sensor to linear HDR frames "
        "(other/x-nrhdr): clipped and too-dark pixels become missing, attenuated pixels are scaled by ND "
        "(paper Eq. 3), a per-pixel state travels with the frame",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, Gst.Caps.from_string(
            raw_template_caps("GRAY16_LE").to_string() + "; " + bayer_template_caps().to_string())),
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS,
                            hdr_template_caps(strict=True)),
    )

    do_gst_base_transform_query = LiveTiming.nr_live_query
    do_before_transform = NrElement.nr_before_transform

    def __init__(self):
        super().__init__()
        self._pool = None
        self.nr_live_init()
        self._profile = None
        self._in_info = None
        self._bayer = None             # (width, height, format) of video/x-bayer input, else None
        self._out_info = None
        self._frames = 0
        self._file_checked = False
        self.set_passthrough(False)
        self.set_in_place(False)

    # ---- state --------------------------------------------------------------------------------------
    @starting
    def do_start(self):
        path = self.settings.profile
        try:
            self._profile = load_profile(path, self.settings.allow_outside_paths)
        except ValueError as e:  # ProfileError is a ValueError
            self.post_error(str(e), kind="settings" if not path else "read")
            return False
        from nrhdr_core import chain
        s = self.settings
        self.nr_warmup(chain.warmup, chain.ChainSettings(mode=s.mode, dark_policy=s.dark_policy),
                       stages=("validity",), elements=True, cfa=self._profile.cfa)
        self._frames = 0
        self._file_checked = False
        return True

    def do_stop(self):
        self._profile = None
        self._in_info = self._out_info = self._bayer = None
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
        if not self.settings.profile:
            return None
        try:
            return load_profile(self.settings.profile, self.settings.allow_outside_paths)
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
            fmt = s.get_string("format") if s.has_field("format") else None
            if s.get_name() == BAYER_MEDIA_TYPE and fmt in BAYER_FORMATS:
                n.set_value("cfa", fmt)          # checked against the profile in set_caps
            elif prof is not None and prof.cfa != "none":
                n.set_value("cfa", prof.cfa)
            return [n]

        def to_raw(s):
            n = Gst.Structure.new_empty("video/x-raw")
            n.set_value("format", "GRAY16_LE")
            copy_fields(s, n)
            out = [n]
            # Bayer too (the profile's phase first): wrong phases and bit depths get named in set_caps
            for fmt in ([prof.cfa] if prof is not None and prof.cfa != "none" else []) + [None]:
                b = bayer_template_caps().get_structure(0).copy()
                copy_fields(s, b)
                if fmt is not None:
                    b.set_value("format", fmt)
                out.append(b)
            return out

        sink = direction == Gst.PadDirection.SINK
        out = transform_caps_by_structure(caps, None, to_hdr if sink else to_raw, self)
        if prof is not None:  # the mask's size only, both ways (empty caps if the other side cannot have it)
            size = f"width=(int){prof.width}, height=(int){prof.height}"
            media = [HDR_MEDIA_TYPE] if sink else ["video/x-raw", BAYER_MEDIA_TYPE]
            out = out.intersect_full(Gst.Caps.from_string("; ".join(f"{m}, {size}" for m in media)),
                                     Gst.CapsIntersectMode.FIRST)
        if filt is not None:
            out = filt.intersect_full(out, Gst.CapsIntersectMode.FIRST)
        self.gst_log(f"transform_caps {direction.value_nick}: {caps.to_string()} -> {out.to_string()}")
        return out

    def do_accept_caps(self, direction, caps):
        ok = GstBase.BaseTransform.do_accept_caps(self, direction, caps)
        if not ok and direction == Gst.PadDirection.SINK and caps is not None and caps.is_fixed():
            try:
                self.post_error(self._refused_caps_text(caps), kind="format")
            except Exception:  # noqa: BLE001 - only an explanation; the answer stands
                pass
        return ok

    def _refused_caps_text(self, caps) -> str:
        """Why a caps event is refused (e.g. GRAY8 from rawvideoparse format=gray8): upstream would only
        say 'not-negotiated'."""
        s = caps.get_structure(0)
        fmt = s.get_string("format") if s.has_field("format") else None
        prof = self._known_profile()
        okw, w = s.get_int("width")
        okh, h = s.get_int("height")
        if (s.get_name() in ("video/x-raw", BAYER_MEDIA_TYPE) and prof is not None and okw and okh
                and (w, h) != (prof.width, prof.height)):
            return self._size_mismatch(prof, w, h)
        if s.get_name() == "video/x-raw" and fmt and fmt != "GRAY16_LE":
            size = f" {w}x{h}" if okw and okh else ""
            return (f"needs raw GRAY16_LE sensor frames (video/x-raw, format=GRAY16_LE) or 8-bit Bayer "
                    f"(video/x-bayer), got {fmt}{size}")
        return (f"cannot accept {caps.to_string()}: needs video/x-raw, format=GRAY16_LE or video/x-bayer, "
                f"format={'|'.join(BAYER_FORMATS)}")

    @guarded("set_caps", False)
    def do_set_caps(self, incaps, outcaps):
        prof = self._profile
        if prof is None:
            self.post_error("no camera profile loaded", kind="settings")
            return False
        st = incaps.get_structure(0)
        if st.get_name() == BAYER_MEDIA_TYPE:
            refusal = self._bayer_refusal(st, prof)
            if refusal:
                self.post_error(refusal, kind="format")
                return False
            self._bayer = (prof.width, prof.height, st.get_string("format"))
            self._in_info = None
        else:
            vi = GstVideo.VideoInfo.new_from_caps(incaps)
            if vi is None:
                self.post_error(f"cannot parse input caps {incaps.to_string()}", kind="format")
                return False
            if (vi.width, vi.height) != (prof.width, prof.height):
                self.post_error(self._size_mismatch(prof, vi.width, vi.height), kind="format")
                return False
            self._in_info, self._bayer = vi, None
        self._out_info = HdrInfo.from_caps(outcaps, element="nrvalidity")
        if self._out_info.cfa != prof.cfa:
            self.post_error(f"output caps cfa={self._out_info.cfa} but profile {self._profile_name()} has cfa "
                            f"{prof.cfa}: the CFA of the frames is the profile's", kind="format")
            return False
        self._pool = HdrPool.for_info(self._pool, self._out_info)
        self.gst_debug(f"caps: {incaps.to_string()} -> {outcaps.to_string()}; pool of "
                       f"{self._out_info.size}-byte frames")
        return True

    def _bayer_refusal(self, st, prof) -> str | None:
        """Why video/x-bayer caps `st` do not fit profile `prof` (None when they do): the Bayer format must
        be the profile's cfa, the profile 8-bit and unpacked, the size the mask's."""
        fmt = st.get_string("format") if st.has_field("format") else None
        name = self._profile_name()
        okw, w = st.get_int("width")
        okh, h = st.get_int("height")
        if okw and okh and (w, h) != (prof.width, prof.height):
            return self._size_mismatch(prof, w, h)
        if prof.cfa == "none":
            return (f"video/x-bayer caps (format={fmt}) need a colour profile, but profile {name} is monochrome "
                    f"(cfa none): set the profile's cfa to the sensor's Bayer phase, or send GRAY16_LE")
        if fmt != prof.cfa:
            return (f"video/x-bayer format={fmt} disagrees with profile {name}'s cfa {prof.cfa} (the sensor's "
                    f"Bayer phase): set the camera or the caps to format={prof.cfa}, or the profile's cfa to "
                    f"{fmt}")
        if prof.bit_depth != 8 or prof.packing != "none":
            what = f"bit_depth {prof.bit_depth}" + (f", packing {prof.packing}" if prof.packing != "none" else "")
            return (f"video/x-bayer caps carry 8-bit codes, but profile {name} says {what}: use an 8-bit "
                    f"profile (bit_depth 8, packing none) for this source, or send the sensor's 16-bit data as "
                    f"GRAY16_LE with the cfa from the profile")
        return None

    def _size_mismatch(self, prof, w, h) -> str:
        name = os.path.basename(str(prof.path)) if prof.path else self.settings.profile
        return f"profile {name} has a {prof.width}x{prof.height} mask but the stream is {w}x{h}"

    # ---- data ---------------------------------------------------------------------------------------
    @guarded("prepare_output_buffer", (Gst.FlowReturn.ERROR, None))
    def do_prepare_output_buffer(self, inbuf):
        if self._out_info is None or self._pool is None:
            self.post_error("no caps negotiated before the first buffer", kind="negotiation")
            return Gst.FlowReturn.NOT_NEGOTIATED, None
        out = self._pool.acquire()
        copy_timestamps(inbuf, out)
        return Gst.FlowReturn.OK, out

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

    def _check_file(self, inbuf) -> bool:
        """First buffer from rawvideoparse: the raw file must be a whole number of frames (rawvideoparse
        drops a partial last frame silently), and a file of unpadded rows read with GStreamer's padded
        default stride (odd widths) gets a hint instead of garbage."""
        self._file_checked = True
        frame = inbuf.get_size()
        try:
            if not self._raw_parser_upstream():
                return True
            ok, total = self.sinkpad.peer_query_duration(Gst.Format.BYTES)
        except Exception:  # noqa: BLE001
            return True
        if not ok or total is None or total <= 0 or frame <= 0:
            return True
        vi = self._in_info
        w, h = vi.width, vi.height
        tight, stride = 2 * w * h, int(vi.stride[0])
        if stride != 2 * w and frame == vi.size and total % tight == 0:
            self.post_error(f"{self._input_name()} holds a whole number of unpadded {w}x{h} GRAY16_LE frames "
                            f"({total // tight} x {tight} bytes), but rawvideoparse reads rows padded to "
                            f"{stride} bytes (GStreamer's default stride for width {w}): set "
                            f"plane-strides=<{2 * w}> on rawvideoparse", kind="format")
            return False
        if total % frame == 0:
            return True
        self.post_error(f"{self._input_name()} is {total} bytes, not a whole number of {frame}-byte {w}x{h} "
                        f"GRAY16_LE frames ({total // frame} frames + {total % frame} bytes): the last frame "
                        f"is truncated", kind="format")
        return False

    def _check_unpacked(self, inbuf) -> None:
        """One GRAY16_LE frame per buffer; a buffer of a packed frame's size says so (aravissrc labels
        Mono12Packed GRAY16_LE)."""
        try:
            check_video_buffer(inbuf, self._in_info)
        except FrameSizeError as e:
            from nrhdr_core.profile import PACKINGS
            n = self._in_info.width * self._in_info.height
            size = inbuf.get_size()
            packed = sorted({k for k, bits in PACKINGS.items() if bits < 16 and size == (n * bits + 7) // 8})
            if not packed:
                raise
            bits = PACKINGS[packed[0]]
            raise FrameSizeError(f"{e}. {size} bytes is a {bits}-bit packed {self._in_info.width}x"
                                 f"{self._in_info.height} frame ({' or '.join(packed)}) labelled GRAY16_LE, "
                                 f"but profile {self._profile_name()} says unpacked {self._profile.bit_depth}-bit "
                                 f"data: set the profile's packing and bit_depth to the camera's pixel format, "
                                 f"or set the camera to an unpacked format (Mono12, Mono16)") from None

    def _profile_name(self) -> str:
        prof = self._profile
        return os.path.basename(str(prof.path)) if prof.path else self.settings.profile

    @contextlib.contextmanager
    def _map_bayer(self, inbuf):
        """An 8-bit Bayer frame as 16-bit codes (H, W) (a per-thread plane): rows of W bytes or of W rounded up
        to 4 (GStreamer's Bayer stride); FrameSizeError for any other buffer size."""
        from nrhdr_core.scratch import planes
        w, h, fmt = self._bayer
        size = inbuf.get_size()
        strides = dict.fromkeys((w, (w + 3) // 4 * 4))
        stride = next((r for r in strides if size == r * h), None)
        if stride is None:
            raise FrameSizeError(f"buffer of {size} bytes does not hold one {w}x{h} 8-bit Bayer ({fmt}) frame: "
                                 f"expected {' or '.join(str(r * h) for r in strides)} bytes (rows of "
                                 f"{' or '.join(str(r) for r in strides)} bytes)")
        ok, mi = inbuf.map(Gst.MapFlags.READ)
        if not ok:
            raise RuntimeError("cannot map the input buffer")
        try:
            codes = planes("nrvalidity.bayer8", (h, w), lambda: np.empty((h, w), np.uint16))
            np.copyto(codes, np.ndarray((h, w), np.uint8, buffer=mi.data, strides=(stride, 1)))
        finally:
            inbuf.unmap(mi)
        yield codes

    @contextlib.contextmanager
    def _map_raw(self, inbuf):
        """The input frame as classify takes it: (H, W) GRAY16_LE words (checked by `_check_unpacked`), an
        8-bit Bayer frame widened to 16 bits, or a packed frame's bytes (checked by `validity.codes`)."""
        if self._bayer is not None:
            with self._map_bayer(inbuf) as raw:
                yield raw
            return
        if self._profile.packing == "none":
            with map_video(inbuf, self._in_info, "<u2", write=False) as raw:
                yield raw
            return
        ok, mi = inbuf.map(Gst.MapFlags.READ)
        if not ok:
            raise RuntimeError("cannot map the input buffer")
        try:
            yield np.frombuffer(mi.data, np.uint8)
        finally:
            inbuf.unmap(mi)

    @guarded(lambda self: f"frame {self._frames}", Gst.FlowReturn.ERROR)
    def do_transform(self, inbuf, outbuf):
        packed = self._profile.packing != "none" or self._bayer is not None
        if not packed:
            self._check_unpacked(inbuf)
        if not packed and not self._file_checked and not self._check_file(inbuf):
            return Gst.FlowReturn.ERROR
        from nrhdr_core import validity
        s = self.settings
        lm = None if s.l_min < 0 else s.l_min
        t0 = time.perf_counter()
        with self.warnings_to_bus(), self._map_raw(inbuf) as raw, \
                map_hdr(outbuf, self._out_info, write=True) as (values, state):
            validity.classify(raw, self._profile, mode=s.mode, l_min=lm, values=values, state=state,
                              dark_policy=s.dark_policy)
        if self.gst_debug_enabled(Gst.DebugLevel.LOG):
            self.gst_log(f"frame {self._frames} pts {Gst.TIME_ARGS(inbuf.pts)}: classified "
                         f"{self._out_info.width}x{self._out_info.height} (mode={s.mode}, l_min="
                         f"{'profile' if lm is None else lm}) in {(time.perf_counter() - t0) * 1e3:.2f} ms")
        self._frames += 1
        return Gst.FlowReturn.OK
