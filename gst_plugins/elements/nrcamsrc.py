"""nrcamsrc: a live camera stand-in emitting raw GRAY16_LE sensor frames at the frame rate.

Run (30 fps live, the simulator's camera over the synthesised scene, into the chain):

    nrhdr profile -o /tmp/cam.json && nrhdr launch nrcamsrc scene=synthetic profile=/tmp/cam.json \
        num-buffers=90 ! nrvalidity profile=/tmp/cam.json ! nrreconstruct method=auto ! nrtonemap ! \
        videoconvert ! fakesink sync=true

Modes: `location=` a clip folder of `nrhdr simulate` (clip.json + clip.raw; `loop`), or `scene=` an HDR
file / "synthetic" rendered with the simulator's motion and noise model (`nrhdr_core.realtime.SceneCamera`:
a path of `frames` frames, repeated; a path of at most SceneCamera.PRERENDER_PIXELS pixels is rendered at start, a
longer one frame by frame when each is due, kept for the repeats only while the whole path fits in
SceneCamera.CACHE_BYTES, so memory stays flat for any `frames`). Live (default): frame k
of the sensor's timeline is exposed during [t0 + k T, t0 + (k+1) T) of the pipeline's running time (t0:
the first request) and pushed when complete, with PTS t0 + k T and duration T, so the LATENCY query
answers one frame period (min) and RING periods (max). A camera driver holds RING frames: when downstream
falls more than that behind, the oldest frames are lost at the source (`dropped`, DISCONT flag; offsets
count sensor frames), so put a `queue` after the source, as after any live source. Not live
(`is-live=false`): frames as fast as downstream takes them, PTS k T, no loss.
"""
from __future__ import annotations

import os
import threading

from ._common import (Gst, GstBase, GstVideo, NrElement, Prop, PropertyTable, gray16_buffer, guarded,
                      load_profile, raw_template_caps, source_caps, starting)
from ._profiles import ALLOW_OUTSIDE_PROP

RING = 4  # frames a camera driver buffers (v4l2src's default); reported as the maximum latency

PROPERTIES = PropertyTable("GstNrCamSrc", [
    Prop("location", str, "", "Clip folder",
         "Clip folder written by 'nrhdr simulate' (clip.json + clip.raw); exclusive with 'scene'"),
    Prop("scene", str, "", "HDR scene",
         "HDR image (OpenEXR, .hdr, ...) or 'synthetic', rendered with the simulator's camera motion and "
         "sensor noise; exclusive with 'location'"),
    Prop("profile", str, "", "Camera profile",
         "Scene mode: camera profile JSON (size, mask, noise); empty = the default profile of width x height "
         "(written to a cache file, see 'profile-path'). Clip mode: ignored (the clip's camera.json)"),
    ALLOW_OUTSIDE_PROP,
    Prop("profile-path", str, "", "Profile in use",
         "The camera profile JSON of the frames (resolved from location / scene / profile / width / height): "
         "give it to nrvalidity profile=...", readonly=True),
    Prop("loop", bool, False, "Loop", "Clip mode: start again at the first frame after the last (else EOS)"),
    Prop("width", int, 640, "Width", "Scene mode without a profile: frame width", minimum=2, maximum=16384),
    Prop("height", int, 480, "Height", "Scene mode without a profile: frame height", minimum=2,
         maximum=16384),
    Prop("fps", int, 0, "Frame rate", "Frames per second; 0 = the clip's rate (clip mode) or 30 (scene mode)",
         minimum=0, maximum=1000),
    Prop("frames", int, 30, "Frames of the path",
         "Scene mode: frames of the camera path (then it repeats); each frame is rendered when it is due",
         minimum=1, maximum=100000),
    Prop("seed", int, 0, "Noise seed", "Scene mode: seed of the sensor noise", minimum=0, maximum=2147483647),
    Prop("exposure", float, 0.0, "Exposure",
         "Scene mode: stops relative to auto exposure (as nrhdr simulate --exposure)", minimum=-20.0,
         maximum=20.0),
    Prop("is-live", bool, True, "Live",
         "Live source: frames at the frame rate on the pipeline clock (a camera); false = as fast as "
         "downstream takes them (a file)"),
    Prop("dropped", "uint64", 0, "Frames dropped",
         "Live: sensor frames lost because downstream had not taken the previous one in time", readonly=True),
])


class NrCamSrc(NrElement, GstBase.BaseSrc):
    __gtype_name__ = "GstNrCamSrc"
    PROPERTIES = PROPERTIES
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
        self._cam = None
        self._vi = None
        self._caps = None
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

    def nr_property_changed(self, name, value):
        if name == "is-live":
            self.set_live(bool(value))

    def nr_read(self, name):
        if name == "dropped":
            return self._dropped
        return self._resolved_profile()

    def _resolved_profile(self) -> str:
        """The profile JSON of the frames; before start resolved from the settings (an app can hand it to
        nrvalidity before playing); "" when it cannot be resolved."""
        if self._profile_used:
            return self._profile_used
        s = self.settings
        try:
            if s.location:
                from nrhdr_core import simulate
                info = simulate.load_clip(s.location, allow_outside=s.allow_outside_paths)
                return str(info["profile_path"])
            if s.scene:
                if s.profile:
                    return os.path.abspath(s.profile)
                return self._cached_default_profile(s.width, s.height)
        except (OSError, ValueError, KeyError):
            pass
        return ""

    # ---- state --------------------------------------------------------------------------------------
    def _fps_value(self, default):
        return self.settings.fps if self.settings.fps > 0 else default

    @starting
    def do_start(self):
        from nrhdr_core import realtime
        s = self.settings
        if bool(s.location) == bool(s.scene):
            self.post_error("set exactly one of 'location' (a clip folder of nrhdr simulate) and "
                            "'scene' (an HDR image or 'synthetic')", kind="settings")
            return False
        if s.location:
            try:
                cam = realtime.ClipCamera(s.location, loop=s.loop, allow_outside=s.allow_outside_paths)
            except (OSError, ValueError, KeyError) as e:
                self.post_error(f"location={s.location}: {e}", kind="read")
                return False
            fps = self._fps_value(cam.fps)
            self._profile_used = cam.profile_path
        else:
            cam = self._scene_camera()
            if cam is None:
                return False
            fps = self._fps_value(30)
        caps = Gst.Caps.from_string(f"video/x-raw, format=GRAY16_LE, width={cam.width}, "
                                    f"height={cam.height}, framerate={fps}/1, pixel-aspect-ratio=1/1")
        self._vi = GstVideo.VideoInfo.new_from_caps(caps)
        self._caps = caps
        self._period = Gst.SECOND // fps
        self._fps_n = fps
        self._cam = cam
        self._reset_counters()
        self._flushing = False
        self.set_blocksize(self._vi.size)
        return True

    def _scene_camera(self):
        from nrhdr_core import realtime
        s = self.settings
        try:
            if s.profile:
                prof = load_profile(s.profile, s.allow_outside_paths)
                self._profile_used = str(prof.path or s.profile)
            else:
                self._profile_used = self._cached_default_profile(s.width, s.height)
                prof = load_profile(self._profile_used)
        except (OSError, ValueError) as e:
            self.post_error(f"profile={s.profile}: {e}", kind="read")
            return None
        try:
            scene, name = realtime.load_scene(s.scene, prof.height, cfa=prof.cfa)
        except (OSError, ValueError) as e:
            self.post_error(f"scene={s.scene}: {e}", kind="read")
            return None
        cam = realtime.SceneCamera(scene, prof, frames=s.frames, seed=s.seed, exposure_stops=s.exposure)
        when = "rendered at start" if cam.prerender() else "each rendered when it is due"
        Gst.info(f"{self.get_name()}: scene {name}, {cam.n}-frame path of {cam.width}x{cam.height} frames, "
                 f"{when} (simulator motion and noise)")
        return cam

    @staticmethod
    def _cached_default_profile(width: int, height: int) -> str:
        """The default profile of this size as a file (nrvalidity needs one), written once:
        ~/.cache/nrhdr/profiles/default_WxH.json."""
        from pathlib import Path

        from nrhdr_core import profile as profiles
        base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nrhdr" / "profiles"
        path = base / f"default_{width}x{height}.json"
        if not path.is_file():
            base.mkdir(parents=True, exist_ok=True)
            profiles.save(profiles.default(height, width, seed=1), path)
        return str(path)

    def do_stop(self):
        self._cam = None
        self._profile_used = ""
        return True

    def do_get_caps(self, filt):
        return source_caps(self.srcpad, getattr(self, "_caps", None) if self._cam is not None else None, filt)

    def do_is_seekable(self):
        return False

    def do_gst_base_src_query(self, query):
        if query.type == Gst.QueryType.LATENCY and self._cam is not None:
            if self.settings.is_live:
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

    def _live_frame(self):
        """Live: the index of the next frame to push, skipping frames downstream missed (lost in the
        camera's ring): (frame index, discont)."""
        clock = self.get_clock()
        k = self._next
        if clock is None:
            return k, False
        now = clock.get_time() - self.get_base_time()
        if self._origin is None:
            self._origin = now
        if now >= self._origin + self._t(k + 1 + RING):       # frame k was overwritten in the ring
            newest = (now - self._origin) * self._fps_n // Gst.SECOND - 1
            oldest = newest - RING + 1
            if oldest > k:
                self._dropped += oldest - k
                return oldest, True
        return k, False

    def _wait_complete(self, k: int):
        """Live: wait until frame k is complete (its exposure period has passed); FlowReturn."""
        clock = self.get_clock()
        if clock is None:
            return Gst.FlowReturn.OK
        due = self.get_base_time() + self._origin + self._t(k + 1)
        with self._lock:
            if self._flushing:
                return Gst.FlowReturn.FLUSHING
            self._clock_id = clock.new_single_shot_id(due)
        ret, _jitter = Gst.Clock.id_wait(self._clock_id)
        with self._lock:
            self._clock_id = None
            if self._flushing or ret == Gst.ClockReturn.UNSCHEDULED:
                return Gst.FlowReturn.FLUSHING
        return Gst.FlowReturn.OK

    @guarded(lambda self: f"frame {self._next}", (Gst.FlowReturn.ERROR, None))
    def do_create(self, offset, length, buf0):
        cam = self._cam
        if cam is None:
            self.post_error("not started", kind="settings")
            return Gst.FlowReturn.ERROR, None
        live = self.settings.is_live
        k, discont = self._live_frame() if live else (self._next, False)
        frame = cam.frame(k)          # rendered now (scene mode), while frame k is being exposed
        if frame is None:
            return Gst.FlowReturn.EOS, None
        if live:
            ret = self._wait_complete(k)
            if ret != Gst.FlowReturn.OK:
                return ret, None
        pts = self._origin + self._t(k) if live and self._origin is not None else self._t(k)
        buf = gray16_buffer(self._vi, frame, k, pts, self._t(k + 1) - self._t(k))
        if discont or self._pushed == 0:
            buf.set_flags(Gst.BufferFlags.DISCONT)
        self._next = k + 1
        self._pushed += 1
        return Gst.FlowReturn.OK, buf
