"""nrexrsink: records linear HDR frames (`other/x-nrhdr`) as an OpenEXR sequence, one file per frame
(float32 channel "Y", optionally a second channel "state"), written atomically by
`nrhdr_core.io.write_exr`. A failed write posts an error naming the file.

Nothing is lost silently: a location whose extension is not .exr is refused at start (OpenImageIO would
write 8-bit PNG/JPEG clipped to white), and so is a sequence that already has files unless
`overwrite=true` (then the old sequence's files are deleted at start, so old and new frames never mix).
"""
from __future__ import annotations

import os
import re

from ._common import (MUTABLE_READY, ErrorPoster, GObject, Gst, GstBase, HdrInfo, hdr_template_caps,
                      map_hdr)
from ._common import debug_category  # noqa: E402  (issue 11: GST_DEBUG=nrexrsink:6)


def format_location(pattern: str, index: int) -> str:
    """printf-style file name, like multifilesink: 'out/frame_%05d.exr' % index. Raises ValueError."""
    if "%" not in pattern:
        raise ValueError(f"location {pattern!r} has no %d: every frame would overwrite the same file "
                         f"(use e.g. out/frame_%05d.exr)")
    try:
        name = pattern % index
    except (TypeError, ValueError) as e:
        raise ValueError(f"location {pattern!r} is not a printf pattern with one integer (e.g. "
                         f"out/frame_%05d.exr): {e}") from None
    return name


def sequence_regex(pattern: str):
    """(folder, compiled regex) matching the file names `pattern` produces for any index (printf %d, %05d,
    %i, ...; %% is a literal %), or None when the folder part itself holds a conversion."""
    folder, base = os.path.split(pattern)
    if "%" in folder.replace("%%", ""):
        return None
    parts = re.split(r"(%%|%[-+ 0#]*\d*[di])", base)
    rx = "".join("%" if t == "%%" else (r"[-+ ]*\d+" if t.startswith("%") else re.escape(t))
                 for t in parts if t)
    return folder or ".", re.compile(rx)


def sequence_files(pattern: str) -> list[str]:
    """Existing files of the sequence `pattern` (any index), sorted."""
    r = sequence_regex(pattern)
    if r is None:
        return []
    folder, rx = r
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    return sorted(os.path.join(folder, n) for n in names if rx.fullmatch(n))


class NrExrSink(ErrorPoster, GstBase.BaseSink):
    __gtype_name__ = "GstNrExrSink"
    DEBUG_CATEGORY = debug_category("nrexrsink", "nrhdr OpenEXR sequence sink")
    __gstmetadata__ = (
        "nrhdr OpenEXR sequence sink",
        "Sink/Video",
        "Writes linear HDR frames (other/x-nrhdr) as an OpenEXR sequence (float32 channel Y, optional "
        "state channel) so a recording keeps the full dynamic range",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("sink", Gst.PadDirection.SINK, Gst.PadPresence.ALWAYS, hdr_template_caps()),
    )

    def __init__(self):
        super().__init__()
        self._location = "frame_%05d.exr"
        self._write_state = False
        self._start_index = 0
        self._overwrite = False
        self._index = 0
        self._info = None
        self.set_sync(False)

    @GObject.Property(type=str, default="frame_%05d.exr", nick="File location",
                      blurb="printf pattern of the output files, one per frame, e.g. out/frame_%05d.exr; "
                            "missing folders are created",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_READY)
    def location(self):
        return self._location

    @location.setter
    def location(self, value):
        self._location = value or ""

    @GObject.Property(type=bool, default=False, nick="Write state",
                      blurb="Add the per-pixel state byte (docs/ARCHITECTURE.md) as a second channel "
                            "'state', so the recording keeps which pixels were measured, clipped, too dark "
                            "or reconstructed",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_READY)
    def write_state(self):
        return self._write_state

    @write_state.setter
    def write_state(self, value):
        self._write_state = bool(value)

    @GObject.Property(type=int, default=0, minimum=0, maximum=2147483647, nick="Start index",
                      blurb="Number of the first file (the %d in location)",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_READY)
    def index(self):
        return self._start_index

    @index.setter
    def index(self, value):
        self._start_index = int(value)

    @GObject.Property(type=bool, default=False, nick="Overwrite",
                      blurb="Replace an existing recording: at start, delete the files of the sequence "
                            "'location' (any index) so old and new frames never mix. Default false: refuse "
                            "to start when any file of the sequence exists",
                      flags=GObject.ParamFlags.READWRITE | MUTABLE_READY)
    def overwrite(self):
        return self._overwrite

    @overwrite.setter
    def overwrite(self, value):
        self._overwrite = bool(value)

    def do_start(self):
        self.reset_errors()
        try:
            if not self._location:
                self.post_error("no file location set (property 'location')", kind="settings")
                return False
            try:
                a = format_location(self._location, 0)
                b = format_location(self._location, 1)
            except ValueError as e:
                self.post_error(str(e), kind="settings")
                return False
            if a == b:
                self.post_error(f"location {self._location!r} has no %d: every frame would overwrite the "
                                f"same file (use e.g. frame_%05d.exr)", kind="settings")
                return False
            ext = os.path.splitext(a)[1]
            if ext.lower() != ".exr":
                self.post_error(f"location {self._location!r}: nrexrsink writes OpenEXR only, the name ends in "
                                f"{ext or 'no extension'!r}; use .exr (for 8-bit images: nrtonemap ! pngenc ! "
                                f"multifilesink)", kind="settings")
                return False
            first = format_location(self._location, self._start_index)
            old = sequence_files(self._location)
            if os.path.lexists(first) and first not in old:
                old.append(first)
            if old and not self._overwrite:
                self.post_error(f"{os.path.abspath(old[0])} already exists ({len(old)} file(s) of the sequence "
                                f"{self._location!r}): refusing to mix a new recording with an old one; "
                                f"choose another location or set overwrite=true", kind="write")
                return False
            for f in old:       # overwrite=true: the old sequence goes as a whole
                try:
                    os.unlink(f)
                except OSError as e:
                    self.post_error(f"overwrite=true: cannot delete the old file {os.path.abspath(f)}: {e}",
                                    kind="write")
                    return False
            self._index = self._start_index
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("start", e)
            return False

    def do_stop(self):
        self._info = None
        return True

    def do_set_caps(self, caps):
        try:
            self._info = HdrInfo.from_caps(caps)
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("set_caps", e)
            return False

    def do_render(self, buf):
        if self._info is None:
            self.post_error("no caps negotiated before the first buffer", kind="negotiation")
            return Gst.FlowReturn.NOT_NEGOTIATED
        path = "?"
        try:
            from nrhdr_core import io
            path = format_location(self._location, self._index)
            with map_hdr(buf, self._info, write=False) as (values, state):
                io.write_exr(path, values, state if self._write_state else None)
            self.gst_log(f"frame pts {Gst.TIME_ARGS(buf.pts)} -> {path}")  # issue 11: per-frame debug line
            self._index += 1
            return Gst.FlowReturn.OK
        except Exception as e:  # noqa: BLE001
            self.post_error(f"could not write {os.path.abspath(path) if path != '?' else path}: {e}",
                            debug=f"{type(e).__name__}: {e}", kind="write")
            return Gst.FlowReturn.ERROR
