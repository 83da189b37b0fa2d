"""nrexrsink: records linear HDR frames (`other/x-nrhdr`) as an OpenEXR sequence, one file per frame
(float32 channel "Y", or channels "R", "G", "B" for colour frames (layout rgb-f32-u8-planar: camera RGB,
BT.709 primaries, not white balanced), optionally one more channel "state"), each written completely or not at all (a
temporary file renamed into place by `nrhdr_core.io.write_exr`); at EOS every frame received is a whole
file. A failed write posts an error naming the file.

`location` is a printf pattern as multifilesink's: one integer conversion (`%d`, `%05d`, `%i`, `%u`, `%x`,
`%o`, with flags, width and C length modifiers such as `%lu`), `%%` for a literal %, in the file name or in
a folder name; a location without a conversion records one frame (a second frame is an error, never an
overwrite). Nothing is lost silently: a location whose extension is not .exr is refused at start
(OpenImageIO would write 8-bit PNG/JPEG clipped to white), and so is a sequence that already has files
unless `overwrite=true` (then the old sequence's files are deleted at start, so old and new frames never
mix).
"""
from __future__ import annotations

import os
import re

from ._common import (LAYOUTS, FrameSizeError, GstBase, Gst, HdrInfo, NrElement, Prop, PropertyTable, debug_category,
                      guarded, hdr_template_caps, map_hdr, starting)

_CONVERSION = re.compile(r"%%|%(?P<flags>[-+ #0]*)(?P<width>\d*)(?:\.(?P<prec>\d*))?"
                         r"(?P<length>hh|h|ll|l|j|z|t|q|L)?(?P<conv>[a-zA-Z])")
_DIGITS = {"d": r"\d", "i": r"\d", "u": r"\d", "o": "[0-7]", "x": "[0-9a-f]", "X": "[0-9A-F]"}


class LocationPattern:
    """A multifilesink-style `location`: printf text with at most one integer conversion."""

    def __init__(self, pattern: str):
        self.pattern = pattern
        self.parts = []                  # literal texts and one conversion spec (a dict)
        self.conversion = None
        pos = 0
        for m in _CONVERSION.finditer(pattern):
            self.parts.append(pattern[pos:m.start()])
            pos = m.end()
            if m.group(0) == "%%":
                self.parts.append("%")
                continue
            if m.group("conv") not in _DIGITS:
                raise ValueError(f"location {pattern!r}: %{m.group('conv')} is not an integer conversion "
                                 f"(use %d, e.g. out/frame_%05d.exr)")
            if self.conversion is not None:
                raise ValueError(f"location {pattern!r} has more than one integer conversion; use one, e.g. "
                                 f"out/frame_%05d.exr")
            self.conversion = m.groupdict()
            self.parts.append(self.conversion)
        rest = pattern[pos:]
        if "%" in rest:
            raise ValueError(f"location {pattern!r}: a lone '%' (write %% for a literal %)")
        self.parts.append(rest)

    @property
    def numbered(self) -> bool:
        return self.conversion is not None

    def format(self, index: int) -> str:
        out = []
        for p in self.parts:
            if isinstance(p, dict):
                conv = "d" if p["conv"] in "iu" else p["conv"]
                prec = f".{p['prec']}" if p["prec"] is not None else ""
                out.append(f"%{p['flags']}{p['width']}{prec}{conv}" % index)
            else:
                out.append(p)
        return "".join(out)

    def files(self) -> list[str]:
        """Existing files this pattern produces for any index, sorted (the file itself when not numbered)."""
        if not self.numbered:
            return [self.pattern] if os.path.lexists(self.pattern) else []
        comps = self.pattern.split(os.sep)
        k = next(i for i, c in enumerate(comps) if _has_conversion(c))
        head = comps[:k]
        folder = os.sep.join(head) or (os.sep if head == [""] else ".")
        rx = component_regex(comps[k])
        tail = [t.replace("%%", "%") for t in comps[k + 1:]]
        head = [h.replace("%%", "%") for h in head]
        try:
            names = sorted(os.listdir(folder.replace("%%", "%")))
        except OSError:
            return []
        found = (os.sep.join(head + [n] + tail) for n in names if rx.fullmatch(n))
        return [f for f in found if os.path.lexists(f)]


def _has_conversion(text: str) -> bool:
    return any(m.group(0) != "%%" for m in _CONVERSION.finditer(text))


def component_regex(text: str):
    """Regex matching what the printf text `text` (one path component) produces for any index."""
    out, pos = [], 0
    for m in _CONVERSION.finditer(text):
        out.append(re.escape(text[pos:m.start()]))
        pos = m.end()
        if m.group(0) == "%%":
            out.append("%")
            continue
        prefix = "(?:0[xX])?" if "#" in m.group("flags") and m.group("conv") in "xX" else ""
        prefix = "0?" if "#" in m.group("flags") and m.group("conv") == "o" else prefix
        out.append(f" *[-+ ]?{prefix}{_DIGITS.get(m.group('conv'), '.')}+ *")
    out.append(re.escape(text[pos:]))
    return re.compile("".join(out))


def format_location(pattern: str, index: int) -> str:
    """The file name of frame `index` (printf-style, as multifilesink). Raises ValueError."""
    return LocationPattern(pattern).format(index)


def sequence_regex(pattern: str):
    """(folder, compiled regex) matching the file names `pattern` produces for any index, or None when a
    folder name holds the conversion (`LocationPattern.files` handles that case)."""
    folder, base = os.path.split(pattern)
    if _has_conversion(folder):
        return None
    return folder or ".", component_regex(base)


def sequence_files(pattern: str) -> list[str]:
    """Existing files of the sequence `pattern` (any index), sorted."""
    return LocationPattern(pattern).files()


PROPERTIES = PropertyTable("GstNrExrSink", [
    Prop("location", str, "frame_%05d.exr", "File location",
         "printf pattern of the output files, one per frame (one integer conversion: %d, %05d, %u, ...; %% "
         "= a literal %), e.g. out/frame_%05d.exr; missing folders are created"),
    Prop("write-state", bool, False, "Write state",
         "Add the per-pixel state byte (docs/ARCHITECTURE.md) as one more channel 'state' (colour frames: the "
         "mosaic's state, one per photosite), so the recording keeps which pixels were measured, clipped, too "
         "dark or reconstructed"),
    Prop("index", int, 0, "Start index", "Number of the first file (the %d in location)",
         minimum=0, maximum=2147483647),
    Prop("overwrite", bool, False, "Overwrite",
         "Replace an existing recording: at start, delete the files of the sequence 'location' (any index) "
         "so old and new frames never mix. Default false: refuse to start when any file of the sequence "
         "exists"),
])


class NrExrSink(NrElement, GstBase.BaseSink):
    __gtype_name__ = "GstNrExrSink"
    PROPERTIES = PROPERTIES
    DEBUG_CATEGORY = debug_category("nrexrsink", "nrhdr OpenEXR sequence sink")
    __gstmetadata__ = (
        "nrhdr OpenEXR sequence sink",
        "Sink/Video",
        "Writes linear HDR frames (other/x-nrhdr) as an OpenEXR sequence (float32 channel Y, or R, G, B for "
        "colour frames; optional state channel) so a recording keeps the full dynamic range",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS,
                            hdr_template_caps(layouts=LAYOUTS)),
    )

    def __init__(self):
        super().__init__()
        self._pattern = None
        self._index = 0
        self._written = 0
        self._info = None
        self.set_sync(False)

    @starting
    def do_start(self):
        s = self.settings
        if not s.location:
            self.post_error("no file location set (property 'location')", kind="settings")
            return False
        try:
            pattern = LocationPattern(s.location)
        except ValueError as e:
            self.post_error(str(e), kind="settings")
            return False
        ext = os.path.splitext(pattern.format(s.index))[1]
        if ext.lower() != ".exr":
            self.post_error(f"location {s.location!r}: nrexrsink writes OpenEXR only, the name ends in "
                            f"{ext or 'no extension'!r}; use .exr (for 8-bit images: nrtonemap ! pngenc ! "
                            f"multifilesink)", kind="settings")
            return False
        first = pattern.format(s.index)
        old = pattern.files()
        if os.path.lexists(first) and first not in old:
            old.append(first)
        if old and not s.overwrite:
            self.post_error(f"{os.path.abspath(old[0])} already exists ({len(old)} file(s) of the sequence "
                            f"{s.location!r}): refusing to mix a new recording with an old one; "
                            f"choose another location or set overwrite=true", kind="write")
            return False
        for f in old:       # overwrite=true: the old sequence goes as a whole
            try:
                os.unlink(f)
            except OSError as e:
                self.post_error(f"overwrite=true: cannot delete the old file {os.path.abspath(f)}: {e}",
                                kind="write")
                return False
        self._pattern = pattern
        self._index = s.index
        self._written = 0
        return True

    def do_stop(self):
        self._info = None
        return True

    @guarded("set_caps", False)
    def do_set_caps(self, caps):
        self._info = HdrInfo.from_caps(caps, LAYOUTS, element="nrexrsink")
        return True

    def do_render(self, buf):
        if self._info is None:
            self.post_error("no caps negotiated before the first buffer", kind="negotiation")
            return Gst.FlowReturn.NOT_NEGOTIATED
        if self._written and not self._pattern.numbered:
            self.post_error(f"location {self._pattern.pattern!r} has no %d: frame {self._written} would "
                            f"overwrite frame 0 (use e.g. frame_%05d.exr for a sequence)", kind="settings")
            return Gst.FlowReturn.ERROR
        path = "?"
        try:
            from nrhdr_core import io
            path = self._pattern.format(self._index)
            with map_hdr(buf, self._info, write=False) as (values, state):
                io.write_exr(path, values, state if self.settings.write_state else None)
            self.gst_log(f"frame pts {Gst.TIME_ARGS(buf.pts)} -> {path}")
            self._index += 1
            self._written += 1
            return Gst.FlowReturn.OK
        except Exception as e:  # noqa: BLE001
            if isinstance(e, FrameSizeError):
                return self.post_exception(f"frame {self._written}", e)
            self.post_error(f"could not write {os.path.abspath(path) if path != '?' else path}: {e}",
                            debug=f"{type(e).__name__}: {e}", kind="write")
            return Gst.FlowReturn.ERROR
