"""nrimagesrc: raw frames stored as 16-bit gray stills (TIFF, PNG), one per file, as GRAY16_LE video.

Run (a folder of 16-bit TIFFs from any camera through the chain into OpenEXR):

    nrhdr launch nrimagesrc location=stills framerate=30/1 ! nrvalidity profile=cam.json ! nrcrosstalk \
        ! nrreconstruct ! nrexrsink location=out/frame_%05d.exr write-state=true

`location` is a folder (its .tif/.tiff/.png files of one kind in natural order; other files, hidden
files and the mask its camera.json names are not frames) or a printf pattern (`stills/frame_%05d.tif`, from `start-index`, default the lowest
index present). Before the first frame every file's header is checked (`nrhdr_core.io.still_sequence`):
consecutive files, inside the folder, one image of one unsigned 16-bit channel, all of the first file's
size; each frame is checked again as it is read. Frame i (of the pushed frames, loops included) has PTS
i / framerate and the duration to the next; EOS after the last file unless `loop`. Not live, not seekable.
"""
from __future__ import annotations

import re

from ._common import (Gst, GstBase, GstVideo, NrElement, Prop, PropertyTable, gray16_buffer, guarded,
                      raw_template_caps, source_caps, starting)

MAX_FPS = 100000
_FRACTION = re.compile(r"\s*(\d{1,10})\s*(?:/\s*(\d{1,10})\s*)?")

PROPERTIES = PropertyTable("GstNrImageSrc", [
    Prop("location", str, "", "Still sequence",
         "Folder of 16-bit gray stills (.tif, .tiff or .png, one kind, natural order) or a printf pattern "
         "(dir/frame_%05d.tif)"),
    Prop("framerate", str, "30/1", "Frame rate",
         "Frames per second as a fraction N/D (30/1, 30000/1001) or an integer: the caps' framerate and the "
         "timestamps (PTS = i / framerate)"),
    Prop("start-index", int, -1, "Start index",
         "Pattern location: index of the first file; -1 = the lowest index present", minimum=-1,
         maximum=2147483647),
    Prop("loop", bool, False, "Loop", "Start again at the first file after the last (timestamps go on); "
                                      "else EOS"),
    Prop("allow-outside-paths", bool, False, "Allow paths outside",
         "Read files of the sequence that are symbolic links out of its folder; refused by default, since a "
         "received folder could otherwise make the source read files from elsewhere (docs/RELIABILITY.md)"),
    Prop("frames", int, 0, "Frames in the sequence",
         "Number of files in the sequence (known once started; 0 before)", minimum=0, maximum=2147483647,
         readonly=True),
])


def parse_framerate(text: str) -> tuple[int, int]:
    """(N, D) of `N/D` or `N`; ValueError naming what is wrong."""
    m = _FRACTION.fullmatch(text or "")
    if m is None:
        raise ValueError(f"{text!r} is not a frame rate: give N/D (30/1, 30000/1001) or an integer")
    n, d = int(m.group(1)), int(m.group(2) or 1)
    if n < 1 or d < 1 or n > MAX_FPS * d:
        raise ValueError(f"{text!r}: the frame rate must be positive and at most {MAX_FPS} frames/s")
    return n, d


class NrImageSrc(NrElement, GstBase.BaseSrc):
    __gtype_name__ = "GstNrImageSrc"
    PROPERTIES = PROPERTIES
    __gstmetadata__ = (
        "nrhdr raw still sequence source",
        "Source/Video",
        "Raw GRAY16_LE frames read from a sequence of 16-bit gray TIFF / PNG stills (any camera's raw "
        "frames, one per file), timestamped at the given frame rate",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS,
                            raw_template_caps("GRAY16_LE")),
    )

    def __init__(self):
        super().__init__()
        self._seq = None
        self._vi = None
        self._caps = None
        self._next = 0
        self.set_live(False)
        self.set_format(Gst.Format.TIME)

    def nr_read(self, name):
        return len(self._seq) if self._seq is not None else 0

    @starting
    def do_start(self):
        from nrhdr_core import io
        s = self.settings
        try:
            fps_n, fps_d = parse_framerate(s.framerate)
        except ValueError as e:
            self.post_error(f"framerate={s.framerate}: {e}", kind="settings")
            return False
        if not s.location:
            self.post_error("location is empty: set a folder of 16-bit stills or a pattern such as "
                            "frame_%05d.tif", kind="settings")
            return False
        try:
            seq = io.still_sequence(s.location, s.start_index, allow_outside=s.allow_outside_paths)
        except (OSError, ValueError) as e:
            self.post_error(f"location={s.location}: {e}", kind="read")
            return False
        caps = Gst.Caps.from_string(f"video/x-raw, format=GRAY16_LE, width={seq.width}, height={seq.height}, "
                                    f"framerate={fps_n}/{fps_d}, pixel-aspect-ratio=1/1")
        self._vi = GstVideo.VideoInfo.new_from_caps(caps)
        self._caps = caps
        self._fps = (fps_n, fps_d)
        self._seq = seq
        self._next = 0
        self.set_blocksize(self._vi.size)
        Gst.info(f"{self.get_name()}: {len(seq)} stills of {seq.width}x{seq.height} from {s.location} at "
                 f"{fps_n}/{fps_d} frames/s")
        return True

    def do_stop(self):
        self._seq = None
        return True

    def do_get_caps(self, filt):
        return source_caps(self.srcpad, self._caps if self._seq is not None else None, filt)

    def do_is_seekable(self):
        return False

    def _t(self, k: int) -> int:
        """PTS of pushed frame k (ns, exact integer arithmetic)."""
        n, d = self._fps
        return k * Gst.SECOND * d // n

    @guarded(lambda self: f"frame {self._next}", (Gst.FlowReturn.ERROR, None))
    def do_create(self, offset, length, buf0):
        seq = self._seq
        if seq is None:
            self.post_error("not started", kind="settings")
            return Gst.FlowReturn.ERROR, None
        k = self._next
        if k >= len(seq) and not self.settings.loop:
            return Gst.FlowReturn.EOS, None
        try:
            frame = seq.read(k % len(seq))
        except (OSError, ValueError) as e:
            self.post_error(f"location={seq.location}: frame {k}: {e}", kind="read")
            return Gst.FlowReturn.ERROR, None
        buf = gray16_buffer(self._vi, frame, k, self._t(k), self._t(k + 1) - self._t(k))
        if k == 0:
            buf.set_flags(Gst.BufferFlags.DISCONT)
        self._next = k + 1
        return Gst.FlowReturn.OK, buf
