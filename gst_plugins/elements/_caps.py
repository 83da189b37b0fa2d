"""Caps of the elements: the HDR frame media type `other/x-nrhdr` (docs/ARCHITECTURE.md), raw gray video
templates and structure-by-structure caps transforms."""
from __future__ import annotations

import dataclasses

from ._gst import Gst, np

HDR_MEDIA_TYPE = "other/x-nrhdr"
# The one frame layout: float32 values (4*W*H bytes, row-major, no padding) then uint8 state (W*H bytes),
# in one contiguous buffer of 5*W*H bytes. Caps without a `layout` field mean this layout too.
HDR_LAYOUT = "f32-u8-planar"
# Fields a video stream keeps through the chain (raw -> HDR -> display).
STREAM_FIELDS = ("width", "height", "framerate", "pixel-aspect-ratio", "interlace-mode")
INT_RANGE = "(int)[1,2147483647]"
FPS_RANGE = "(fraction)[0/1,2147483647/1]"


def hdr_template_caps(strict: bool = False) -> Gst.Caps:
    """`other/x-nrhdr, layout=(string)f32-u8-planar, width, height, framerate`. Unless `strict`, a second
    structure without `layout` accepts caps that omit the field (same layout)."""
    body = f"width={INT_RANGE}, height={INT_RANGE}, framerate={FPS_RANGE}"
    text = f"{HDR_MEDIA_TYPE}, layout=(string){HDR_LAYOUT}, {body}"
    if not strict:
        text += f"; {HDR_MEDIA_TYPE}, {body}"
    return Gst.Caps.from_string(text)


def hdr_transform_templates() -> tuple:
    """The sink and src pad templates of an element that takes and gives HDR frames."""
    return (Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, hdr_template_caps()),
            Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS, hdr_template_caps()))


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
    """The fixed `other/x-nrhdr` caps of a stream."""
    width: int
    height: int
    fps_n: int
    fps_d: int
    white: float | None
    profile: str | None
    diffuse_white: float | None = None   # regular pixels' white (caps field diffuse-white), nrvalidity
    layout: str = HDR_LAYOUT

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def size(self) -> int:
        """Bytes of one frame: 4*W*H float32 values then W*H state bytes."""
        return 5 * self.pixels

    @property
    def state_offset(self) -> int:
        return 4 * self.pixels

    @classmethod
    def from_caps(cls, caps: Gst.Caps) -> "HdrInfo":
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
        if s.has_field("layout"):
            layout = s.get_string("layout")
            if layout != HDR_LAYOUT:
                raise ValueError(f"{HDR_MEDIA_TYPE} layout {layout!r} is not supported (only {HDR_LAYOUT}: "
                                 f"float32 values then uint8 state, one block)")

        def positive(field):
            if s.has_field(field):
                ok, v = s.get_double(field)
                if ok and np.isfinite(v) and v > 0:
                    return float(v)
            return None

        prof = s.get_string("profile") if s.has_field("profile") else None
        return cls(w, h, fn, fd, positive("white"), prof or None, positive("diffuse-white"))
