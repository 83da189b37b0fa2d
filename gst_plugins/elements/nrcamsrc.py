"""nrcamsrc: a live camera stand-in emitting raw GRAY16_LE sensor frames at the frame rate.

Run (30 fps live, the simulator's camera over the synthesised scene, into the chain):

    nrhdr profile -o /tmp/cam.json && nrhdr launch nrcamsrc scene=synthetic profile=/tmp/cam.json \
        num-buffers=90 ! nrvalidity profile=/tmp/cam.json ! nrreconstruct method=auto ! nrtonemap ! \
        videoconvert ! fakesink sync=true

Modes: `location=` a clip folder of `nrhdr simulate` (clip.json + clip.raw; `loop`), or `scene=` an HDR
file / "synthetic" rendered with the simulator's motion and noise model (`nrhdr_core.realtime.SceneCamera`:
`frames` frames rendered once at start, then repeated). Live (default): frame k of the sensor's timeline
is exposed during [t0 + k T, t0 + (k+1) T) of the pipeline's running time (t0: the first request) and
pushed when complete, with PTS t0 + k T and duration T, so the LATENCY query answers one frame period
(min) and RING periods (max). A camera driver holds RING frames: when downstream falls more than that
behind, the oldest frames are lost at the source (`dropped`, DISCONT flag; offsets count sensor frames),
so put a `queue` after the source, as after any live source. Not live
(`is-live=false`): frames as fast as downstream takes them, PTS k T, no loss.
"""
from __future__ import annotations

import os
import threading

from ._common import (MUTABLE_READY, ErrorPoster, GObject, Gst, GstBase, GstVideo, np,
                      raw_template_caps)

RING = 4  # frames a camera driver buffers (v4l2src's default); reported as the maximum latency
_RW = GObject.ParamFlags.READWRITE
_RO = GObject.ParamFlags.READABLE


class NrCamSrc(ErrorPoster, GstBase.BaseSrc):
    __gtype_name__ = "GstNrCamSrc"
    __gstmetadata__ = (
        "nrhdr live camera stand-in",
        "Source/Video",
        "Live raw GRAY16_LE frames of a non-regular ND camera at the frame rate, timestamped with the "
        "pipeline's running time: a clip folder of 'nrhdr simulate' or an HDR scene rendered with the "
        "simulator's motion and noise model",
        "nrhdr project",
    )
    __gsttemplates__ = (
        Gst.PadTemplate.new("src", Gst.PadDirection.SRC, Gst.PadPresence.ALWAYS,
                            raw_template_caps("GRAY16_LE")),
    )

    def __init__(self):
        super().__init__()
        self._location = ""
        self._scene = ""
        self._profile = ""
        self._loop = False
        self._width, self._height, self._fps = 640, 480, 0
        self._frames = 30
        self._seed = 0
        self._exposure = 0.0
        self._live = True
        self._cam = None
        self._vi = None
        self._profile_used = ""
        self._lock = threading.Lock()
        self._clock_id = None
        self._flushing = False
        self._reset_counters()
        self.set_live(True)
        self.set_format(Gst.Format.TIME)

    def _reset_counters(self):
        self._next = 0          # next sensor frame index
        self._origin = None     # running time of frame 0 (live)
        self._pushed = 0
        self._dropped = 0

    # ---- properties ---------------------------------------------------------------------------------
    @GObject.Property(type=str, default="", nick="Clip folder",
                      blurb="Clip folder written by 'nrhdr simulate' (clip.json + clip.raw); exclusive "
                            "with 'scene'", flags=_RW | MUTABLE_READY)
    def location(self):
        return self._location

    @location.setter
    def location(self, value):
        self._location = value or ""

    @GObject.Property(type=str, default="", nick="HDR scene",
                      blurb="HDR image (OpenEXR, .hdr, ...) or 'synthetic', rendered with the simulator's "
                            "camera motion and sensor noise; exclusive with 'location'",
                      flags=_RW | MUTABLE_READY)
    def scene(self):
        return self._scene

    @scene.setter
    def scene(self, value):
        self._scene = value or ""

    @GObject.Property(type=str, default="", nick="Camera profile",
                      blurb="Scene mode: camera profile JSON (size, mask, noise); empty = the default "
                            "profile of width x height (written to a cache file, see 'profile-path'). "
                            "Clip mode: ignored (the clip's camera.json)", flags=_RW | MUTABLE_READY)
    def profile(self):
        return self._profile

    @profile.setter
    def profile(self, value):
        self._profile = value or ""

    @GObject.Property(type=str, default="", nick="Profile in use",
                      blurb="The camera profile JSON of the frames (read-only; resolved from location / "
                            "scene / profile / width / height): give it to nrvalidity profile=...",
                      flags=_RO)
    def profile_path(self):
        if self._profile_used:
            return self._profile_used
        try:  # before start: resolve it (an app can hand it to nrvalidity before playing)
            if self._location:
                from nrhdr_core import simulate
                info = simulate.load_clip(self._location)
                return os.path.join(info["dir"], info.get("profile", "camera.json"))
            if self._scene:
                if self._profile:
                    return os.path.abspath(self._profile)
                from nrhdr_core import profile as profiles
                return self._cached_default_profile(profiles.default(self._height, self._width, seed=1))
        except (OSError, ValueError, KeyError):
            pass
        return ""

    @GObject.Property(type=bool, default=False, nick="Loop",
                      blurb="Clip mode: start again at the first frame after the last (else EOS)",
                      flags=_RW | MUTABLE_READY)
    def loop(self):
        return self._loop

    @loop.setter
    def loop(self, value):
        self._loop = bool(value)

    @GObject.Property(type=int, default=640, minimum=2, maximum=16384, nick="Width",
                      blurb="Scene mode without a profile: frame width", flags=_RW | MUTABLE_READY)
    def width(self):
        return self._width

    @width.setter
    def width(self, value):
        self._width = int(value)

    @GObject.Property(type=int, default=480, minimum=2, maximum=16384, nick="Height",
                      blurb="Scene mode without a profile: frame height", flags=_RW | MUTABLE_READY)
    def height(self):
        return self._height

    @height.setter
    def height(self, value):
        self._height = int(value)

    @GObject.Property(type=int, default=0, minimum=0, maximum=1000, nick="Frame rate",
                      blurb="Frames per second; 0 = the clip's rate (clip mode) or 30 (scene mode)",
                      flags=_RW | MUTABLE_READY)
    def fps(self):
        return self._fps

    @fps.setter
    def fps(self, value):
        self._fps = int(value)

    @GObject.Property(type=int, default=30, minimum=1, maximum=100000, nick="Frames rendered",
                      blurb="Scene mode: frames of the camera path, rendered once at start and repeated",
                      flags=_RW | MUTABLE_READY)
    def frames(self):
        return self._frames

    @frames.setter
    def frames(self, value):
        self._frames = int(value)

    @GObject.Property(type=int, default=0, minimum=0, maximum=2147483647, nick="Noise seed",
                      blurb="Scene mode: seed of the sensor noise", flags=_RW | MUTABLE_READY)
    def seed(self):
        return self._seed

    @seed.setter
    def seed(self, value):
        self._seed = int(value)

    @GObject.Property(type=float, default=0.0, minimum=-20.0, maximum=20.0, nick="Exposure",
                      blurb="Scene mode: stops relative to auto exposure (as nrhdr simulate --exposure)",
                      flags=_RW | MUTABLE_READY)
    def exposure(self):
        return self._exposure

    @exposure.setter
    def exposure(self, value):
        self._exposure = float(value)

    @GObject.Property(type=bool, default=True, nick="Live",
                      blurb="Live source: frames at the frame rate on the pipeline clock (a camera); "
                            "false = as fast as downstream takes them (a file)", flags=_RW | MUTABLE_READY)
    def is_live(self):
        return self._live

    @is_live.setter
    def is_live(self, value):
        self._live = bool(value)
        self.set_live(self._live)

    @GObject.Property(type=GObject.TYPE_UINT64, default=0, nick="Frames dropped",
                      blurb="Live: sensor frames lost because downstream had not taken the previous "
                            "one in time (read-only)", flags=_RO)
    def dropped(self):
        return self._dropped

    # ---- state --------------------------------------------------------------------------------------
    def _fps_value(self, default):
        return self._fps if self._fps > 0 else default

    def do_start(self):
        self.reset_errors()
        try:
            from nrhdr_core import realtime
            if bool(self._location) == bool(self._scene):
                self.post_error("set exactly one of 'location' (a clip folder of nrhdr simulate) and "
                                "'scene' (an HDR image or 'synthetic')", kind="settings")
                return False
            if self._location:
                try:
                    cam = realtime.ClipCamera(self._location, loop=self._loop)
                except (OSError, ValueError, KeyError) as e:
                    self.post_error(f"location={self._location}: {e}", kind="read")
                    return False
                fps = self._fps_value(cam.fps)
                self._profile_used = cam.profile_path
            else:
                cam = self._scene_camera()
                if cam is None:
                    return False
                fps = self._fps_value(30)
            caps = Gst.Caps.from_string(f"video/x-raw, format=GRAY16_LE, width={cam.width}, "
                                        f"height={cam.height}, framerate={fps}/1, "
                                        f"pixel-aspect-ratio=1/1")
            self._vi = GstVideo.VideoInfo.new_from_caps(caps)
            self._caps = caps
            self._period = Gst.SECOND // fps
            self._fps_n = fps
            self._cam = cam
            self._reset_counters()
            self._flushing = False
            self.set_blocksize(self._vi.size)
            return True
        except Exception as e:  # noqa: BLE001
            self.post_exception("start", e)
            return False

    def _scene_camera(self):
        from nrhdr_core import profile as profiles, realtime
        try:
            if self._profile:
                prof = profiles.load(self._profile)
                self._profile_used = str(prof.path or self._profile)
            else:
                prof = profiles.default(self._height, self._width, seed=1)
                self._profile_used = self._cached_default_profile(prof)
        except (OSError, ValueError) as e:
            self.post_error(f"profile={self._profile}: {e}", kind="read")
            return None
        try:
            scene, name = realtime.load_scene(self._scene, prof.height)
        except (OSError, ValueError) as e:
            self.post_error(f"scene={self._scene}: {e}", kind="read")
            return None
        cam = realtime.SceneCamera(scene, prof, frames=self._frames, seed=self._seed,
                                   exposure_stops=self._exposure)
        text = (f"{self.get_name()}: rendering {cam.n} frames {cam.width}x{cam.height} of scene {name} "
                f"(simulator motion and noise; once, before playing)")
        Gst.info(text)
        if cam.n * cam.width * cam.height > 10_000_000:  # takes seconds: say so on the bus too
            self.message_full(Gst.MessageType.INFO, Gst.core_error_quark(), int(Gst.CoreError.FAILED), text,
                              text, __file__, "start", 0)  # gst-launch prints an INFO's debug text only
        cam.render_all()
        return cam

    @staticmethod
    def _cached_default_profile(prof) -> str:
        """Write the default profile once per size (nrvalidity needs it as a file): ~/.cache/nrhdr/."""
        from pathlib import Path

        from nrhdr_core import profile as profiles
        base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nrhdr" / "profiles"
        path = base / f"default_{prof.width}x{prof.height}.json"
        if not path.is_file():
            base.mkdir(parents=True, exist_ok=True)
            profiles.save(prof, path)
        return str(path)

    def do_stop(self):
        self._cam = None
        self._profile_used = ""
        return True

    def do_get_caps(self, filt):
        caps = getattr(self, "_caps", None) if self._cam is not None else None
        if caps is None:
            caps = self.srcpad.get_pad_template_caps()
        if filt is not None:
            caps = filt.intersect_full(caps, Gst.CapsIntersectMode.FIRST)
        return caps

    def do_is_seekable(self):
        return False

    def do_gst_base_src_query(self, query):
        if query.type == Gst.QueryType.LATENCY and self._cam is not None:
            if self._live:
                # a frame is complete one period after its PTS (min); it stays available while the
                # camera's ring of RING frames holds it (max)
                query.set_latency(True, self._period, RING * self._period)
            else:
                query.set_latency(False, 0, Gst.CLOCK_TIME_NONE)
            return True
        return GstBase.BaseSrc.do_query(self, query)

    def do_unlock(self):
        with self._lock:
            self._flushing = True
            if self._clock_id is not None:
                Gst.Clock.id_unschedule(self._clock_id)
        return True

    def do_unlock_stop(self):
        with self._lock:
            self._flushing = False
        return True

    # ---- data ---------------------------------------------------------------------------------------
    def _t(self, k: int) -> int:
        """Start of sensor frame k relative to frame 0 (ns, exact for any integer rate)."""
        return k * Gst.SECOND // self._fps_n

    def _wait_live(self):
        """Live: wait until frame self._next is complete, skipping frames downstream missed; returns
        (FlowReturn, frame index, pts, discont)."""
        clock = self.get_clock()
        if clock is None:
            return Gst.FlowReturn.OK, self._next, self._t(self._next), False
        base = self.get_base_time()
        now = clock.get_time() - base
        if self._origin is None:
            self._origin = now
        t = self._t
        k = self._next
        discont = False
        if now >= self._origin + t(k + 1 + RING):       # frame k was overwritten in the ring
            newest = (now - self._origin) * self._fps_n // Gst.SECOND - 1
            oldest = newest - RING + 1
            if oldest > k:
                self._dropped += oldest - k
                k, discont = oldest, True
        due = base + self._origin + t(k + 1)
        with self._lock:
            if self._flushing:
                return Gst.FlowReturn.FLUSHING, k, 0, False
            self._clock_id = clock.new_single_shot_id(due)
        ret, _jitter = Gst.Clock.id_wait(self._clock_id)
        with self._lock:
            self._clock_id = None
            if self._flushing or ret == Gst.ClockReturn.UNSCHEDULED:
                return Gst.FlowReturn.FLUSHING, k, 0, False
        return Gst.FlowReturn.OK, k, self._origin + t(k), discont

    def do_create(self, offset, length, buf0):
        try:
            cam = self._cam
            if cam is None:
                self.post_error("not started", kind="settings")
                return Gst.FlowReturn.ERROR, None
            if self._live:
                ret, k, pts, discont = self._wait_live()
                if ret != Gst.FlowReturn.OK:
                    return ret, None
            else:
                k, pts, discont = self._next, self._t(self._next), False
            frame = cam.frame(k)
            if frame is None:
                return Gst.FlowReturn.EOS, None
            vi = self._vi
            buf = Gst.Buffer.new_allocate(None, vi.size, None)
            ok, mi = buf.map(Gst.MapFlags.WRITE)
            if not ok:
                raise RuntimeError("cannot map a new buffer for writing")
            try:
                dst = np.ndarray((vi.height, vi.width), "<u2", buffer=mi.data, offset=vi.offset[0],
                                 strides=(vi.stride[0], 2))
                np.copyto(dst, frame)
            finally:
                buf.unmap(mi)
            buf.pts = pts
            buf.dts = Gst.CLOCK_TIME_NONE
            buf.duration = self._t(k + 1) - self._t(k)
            buf.offset = k
            buf.offset_end = k + 1
            if discont or self._pushed == 0:
                buf.set_flags(Gst.BufferFlags.DISCONT)
            self._next = k + 1
            self._pushed += 1
            return Gst.FlowReturn.OK, buf
        except Exception as e:  # noqa: BLE001
            return self.post_exception(f"frame {self._next}", e), None
