"""Caps of the elements: the HDR frame media type `other/x-nrhdr` (docs/ARCHITECTURE.md "The HDR frame between
elements"; its two layouts: mosaic/monochrome frames and colour frames), raw gray and Bayer video templates and
structure-by-structure caps transforms."""
from __future__ import annotations

import dataclasses

from nrhdr_core.cfa import PATTERNS

from ._gst import Gst, np

HDR_MEDIA_TYPE = "other/x-nrhdr"
# A one-value-per-pixel frame (monochrome, or a CFA mosaic with the caps field `cfa`): float32 values (4*W*H
# bytes, row-major, no padding) then uint8 state (W*H bytes), one contiguous block of 5*W*H bytes. Caps
# without a `layout` field mean this layout.
HDR_LAYOUT = "f32-u8-planar"
# A colour frame: float32 planes R, G, B (4*W*H bytes each) then the mosaic's uint8 state (W*H bytes), one
# block of 13*W*H bytes.
RGB_LAYOUT = "rgb-f32-u8-planar"
LAYOUT_CHANNELS = {HDR_LAYOUT: 1, RGB_LAYOUT: 3}
LAYOUTS = tuple(LAYOUT_CHANNELS)
# Bayer video (GStreamer's 8-bit `video/x-bayer`; the four phases of nrhdr_core.cfa.PATTERNS)
BAYER_MEDIA_TYPE = "video/x-bayer"
BAYER_FORMATS = PATTERNS
# Fields a video stream keeps through the chain (raw -> HDR -> display).
STREAM_FIELDS = ("width", "height", "framerate", "pixel-aspect-ratio", "interlace-mode")
INT_RANGE = "(int)[1,2147483647]"
FPS_RANGE = "(fraction)[0/1,2147483647/1]"


class CapsError(ValueError):
    """Caps an element cannot take (a layout it does not process, a Bayer format that disagrees with the
    profile...): posted as a format error naming the element and what is wrong."""


def _layout_list(layouts) -> tuple:
    layouts = (layouts,) if isinstance(layouts, str) else tuple(layouts)
    bad = [x for x in layouts if x not in LAYOUT_CHANNELS]
    if bad or not layouts:
        raise ValueError(f"HDR layouts must be of {', '.join(LAYOUTS)}, got {bad or layouts}")
    return layouts


def hdr_template_caps(strict: bool = False, layouts=(HDR_LAYOUT,)) -> Gst.Caps:
    """`other/x-nrhdr, layout=(string){<layouts>}, width, height, framerate` (`layouts`: of LAYOUTS; the
    `cfa` field is free). Unless `strict`, a second structure without `layout` accepts caps that omit the
    field (which means f32-u8-planar); `HdrInfo.from_caps(caps, layouts)` refuses the others by name."""
    layouts = _layout_list(layouts)
    body = f"width={INT_RANGE}, height={INT_RANGE}, framerate={FPS_RANGE}"
    value = layouts[0] if len(layouts) == 1 else "{ " + ", ".join(layouts) + " }"
    text = f"{HDR_MEDIA_TYPE}, layout=(string){value}, {body}"
    if not strict:   # first, so that caps without the field stay fixed when intersected with the template
        text = f"{HDR_MEDIA_TYPE}, {body}; {text}"
    return Gst.Caps.from_string(text)


def hdr_transform_templates(sink_layouts=(HDR_LAYOUT,), src_layouts=None) -> tuple:
    """The sink and src pad templates of an element that takes and gives HDR frames (`src_layouts`
    None = the sink's)."""
    src_layouts = sink_layouts if src_layouts is None else src_layouts
    return (Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS,
                                hdr_template_caps(layouts=sink_layouts)),
            Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS,
                                hdr_template_caps(layouts=src_layouts)))


def bayer_template_caps() -> Gst.Caps:
    """`video/x-bayer, format={rggb, bggr, grbg, gbrg}, width, height, framerate` (8-bit Bayer: the only
    Bayer caps of GStreamer 1.22, aravissrc and v4l2src)."""
    return Gst.Caps.from_string(f"{BAYER_MEDIA_TYPE}, format=(string){{ {', '.join(BAYER_FORMATS)} }}, "
                                f"width={INT_RANGE}, height={INT_RANGE}, framerate={FPS_RANGE}")


def raw_template_caps(formats: str, extra: str = "") -> Gst.Caps:
    """`video/x-raw, format=<formats>, width, height, framerate[, extra]` (formats: one name or `{ A, B }`)."""
    return Gst.Caps.from_string(f"video/x-raw, format=(string){formats}, width={INT_RANGE}, "
                                f"height={INT_RANGE}, framerate={FPS_RANGE}" + (f", {extra}" if extra else ""))


def source_caps(srcpad: Gst.Pad, caps: Gst.Caps | None, filt: Gst.Caps | None) -> Gst.Caps:
    """A source's do_get_caps: its fixed caps once started (`caps`), else its pad template, with the
    filter's order first."""
    caps = srcpad.get_pad_template_caps() if caps is None else caps
    return caps if filt is None else filt.intersect_full(caps, Gst.CapsIntersectMode.FIRST)


def copy_fields(src: Gst.Structure, dst: Gst.Structure, fields=STREAM_FIELDS) -> None:
    for f in fields:
        if src.has_field(f):
            dst.set_value(f, src.get_value(f))


def transform_caps_by_structure(caps: Gst.Caps, filt: Gst.Caps | None, make, element=None) -> Gst.Caps:
    """Map each structure of `caps` with `make(structure) -> list[Gst.Structure]`, then intersect with the
    filter (first-caps order kept). An exception becomes an element error (if `element`) and empty caps,
    never a Python traceback with NULL caps."""
    try:
        out = Gst.Caps.new_empty()
        for i in range(caps.get_size()):
            for s in make(caps.get_structure(i)):
                out.append_structure(s)
        if filt is not None:
            out = filt.intersect_full(out, Gst.CapsIntersectMode.FIRST)
        return out
    except Exception as e:  # noqa: BLE001
        if element is not None:
            element.post_exception("transform_caps", e)
        return Gst.Caps.new_empty()


@dataclasses.dataclass(frozen=True)
class HdrInfo:
    """The fixed `other/x-nrhdr` caps of a stream: size, frame rate, white, profile, layout and CFA."""
    width: int
    height: int
    fps_n: int
    fps_d: int
    white: float | None
    profile: str | None
    diffuse_white: float | None = None   # regular pixels' white (caps field diffuse-white), nrvalidity
    layout: str = HDR_LAYOUT             # of LAYOUTS
    cfa: str = "none"                    # caps field cfa: a Bayer phase (nrhdr_core.cfa.PATTERNS) or "none"

    def __post_init__(self):
        if self.layout not in LAYOUT_CHANNELS:
            raise ValueError(f"{HDR_MEDIA_TYPE} layout {self.layout!r} is not one of {', '.join(LAYOUTS)}")

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def channels(self) -> int:
        """Float planes per frame: 1 (f32-u8-planar: monochrome or mosaic) or 3 (rgb-f32-u8-planar)."""
        return LAYOUT_CHANNELS[self.layout]

    @property
    def colour(self) -> bool:
        """True for a frame of three colour planes (rgb-f32-u8-planar)."""
        return self.channels == 3

    @property
    def mosaic(self) -> bool:
        """True for a one-plane frame of a colour sensor (a `cfa` other than none)."""
        return self.channels == 1 and self.cfa != "none"

    @property
    def size(self) -> int:
        """Bytes of one frame: 4*channels*W*H float32 values then W*H state bytes."""
        return (4 * self.channels + 1) * self.pixels

    @property
    def state_offset(self) -> int:
        return 4 * self.channels * self.pixels

    @property
    def shape(self) -> tuple:
        """Shape of the values: (H, W), or (3, H, W) for a colour frame."""
        hw = (self.height, self.width)
        return hw if self.channels == 1 else (self.channels,) + hw

    def caps_string(self) -> str:
        """The fixed caps of this frame (size, layout, cfa when colour; framerate when known)."""
        text = f"{HDR_MEDIA_TYPE}, layout=(string){self.layout}, width=(int){self.width}, height=(int){self.height}"
        if self.fps_d > 0:
            text += f", framerate=(fraction){self.fps_n}/{self.fps_d}"
        if self.cfa != "none":
            text += f", cfa=(string){self.cfa}"
        return text

    def replace(self, **kw) -> "HdrInfo":
        return dataclasses.replace(self, **kw)

    @classmethod
    def from_caps(cls, caps: Gst.Caps, layouts=(HDR_LAYOUT,), element: str = "") -> "HdrInfo":
        """The caps' frame; CapsError when their layout is not of `layouts` (what the calling element takes,
        e.g. LAYOUTS for both; `element` names it in the message) or their cfa is not a CFA name."""
        if caps is None or caps.get_size() < 1:
            raise ValueError("no caps")
        s = caps.get_structure(0)
        if s.get_name() != HDR_MEDIA_TYPE:
            raise ValueError(f"caps are {s.get_name()}, expected {HDR_MEDIA_TYPE}")
        okw, w = s.get_int("width")
        okh, h = s.get_int("height")
        if not (okw and okh) or w < 1 or h < 1:
            raise ValueError(f"{HDR_MEDIA_TYPE} caps without a fixed width/height: {caps.to_string()}")
        okf, fn, fd = s.get_fraction("framerate")
        if not okf:
            fn, fd = 0, 1
        layouts = _layout_list(layouts)
        layout = s.get_string("layout") if s.has_field("layout") else HDR_LAYOUT
        who = f"{element} " if element else ""
        if layout not in layouts:
            what = {HDR_LAYOUT: "one float32 plane (monochrome or CFA mosaic) then uint8 state",
                    RGB_LAYOUT: "float32 R, G, B planes then uint8 state"}
            takes = "; ".join(f"{x} ({what[x]})" for x in layouts)
            if layout not in LAYOUT_CHANNELS:
                raise CapsError(f"{who}{HDR_MEDIA_TYPE} layout {layout!r} is not supported: it takes {takes}")
            hint = (" (nrreconstruct makes colour frames of a colour sensor's mosaic frames)"
                    if layout == RGB_LAYOUT else "")
            raise CapsError(f"{who}cannot take {HDR_MEDIA_TYPE} layout {layout} ({what[layout]}): it takes "
                            f"{takes}{hint}")
        cfa = s.get_string("cfa") if s.has_field("cfa") else "none"
        if cfa not in ("none",) + BAYER_FORMATS:
            raise CapsError(f"{who}caps field cfa={cfa!r} is not one of none, {', '.join(BAYER_FORMATS)}")

        def positive(field):
            if s.has_field(field):
                ok, v = s.get_double(field)
                if ok and np.isfinite(v) and v > 0:
                    return float(v)
            return None

        prof = s.get_string("profile") if s.has_field("profile") else None
        return cls(w, h, fn, fd, positive("white"), prof or None, positive("diffuse-white"), layout, cfa)
