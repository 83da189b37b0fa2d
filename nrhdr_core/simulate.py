"""Scene to raw sensor video: camera motion across an HDR scene, captured by the sensor model.

Writes a clip folder (docs/SIMULATOR.md): `clip.raw` (GRAY16_LE, for `filesrc ! rawvideoparse`),
`camera.json` + `camera_mask.png` (the profile), `clip.json` (size, rate, frames), `truth/frame_%05d.exr`
(noise-free, unclipped linear DN: what a perfect chain would output) and, on request,
`raw_png/frame_%05d.png` or `raw_tiff/frame_%05d.tif` (16-bit). Seeded and deterministic.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import io, outputs, profile as profiles, sensor

CLIP_FORMAT = "nrhdr-clip"


@dataclass(frozen=True)
class Motion:
    """Camera path: the view's centre moves by `pan` (fraction of the scene width) left to right and
    the view zooms by `zoom` (1 = none) over the clip; `fov` is the first view's share of the scene."""
    pan: float = 0.15
    tilt: float = 0.05
    zoom: float = 1.25
    fov: float = 0.8

    def validate(self) -> None:
        """ValueError naming the argument when the path cannot be rendered: fov in (0, 1], zoom > 0 and the
        widest view (fov / zoom when zooming out) inside the scene, pan and tilt finite within +-1."""
        for k in ("pan", "tilt", "zoom", "fov"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise ValueError(f"{k} must be a finite number, got {v!r}")
        if not (0 < self.fov <= 1):
            raise ValueError(f"fov must be in (0, 1] (the first view's share of the scene), got {self.fov}")
        if not (self.zoom > 0):
            raise ValueError(f"zoom must be > 0 (1 = none, 2 = twice as close at the end), got {self.zoom}")
        if self.fov / min(self.zoom, 1.0) > 1:
            raise ValueError(f"zoom {self.zoom} with fov {self.fov} would zoom out beyond the scene (fov / zoom "
                             f"= {self.fov / self.zoom:.3g} > 1): use zoom >= fov")
        for k in ("pan", "tilt"):
            if abs(getattr(self, k)) > 1:
                raise ValueError(f"{k} must be within -1..1 (a fraction of the scene), got {getattr(self, k)}")


EXPOSURE_STOPS_MAX = 30.0   # |exposure| beyond 30 stops is all black or all clipped on any sensor


def check_args(frames: int, fps: int, exposure_stops: float, motion: Motion, sequence=None) -> None:
    """Validate simulate_clip's arguments up front (before anything is written); ValueError names them."""
    if not (isinstance(frames, (int, np.integer)) and not isinstance(frames, bool) and frames >= 1):
        raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
    if not (isinstance(fps, (int, np.integer)) and not isinstance(fps, bool) and 1 <= fps <= 10000):
        raise ValueError(f"fps must be an integer in 1..10000, got {fps!r}")
    if not (isinstance(exposure_stops, (int, float)) and math.isfinite(exposure_stops)
            and abs(exposure_stops) <= EXPOSURE_STOPS_MAX):
        raise ValueError(f"exposure must be within -{EXPOSURE_STOPS_MAX:g}..{EXPOSURE_STOPS_MAX:g} stops, got "
                         f"{exposure_stops!r}")
    if sequence not in (None, "png", "tiff"):
        raise ValueError(f"sequence must be 'png' or 'tiff', got {sequence!r}")
    motion.validate()


# What simulate_clip writes into a clip folder (outputs.staged_folder: with overwrite, only these are replaced).
CLIP_OUTPUTS = io.owned_by_patterns(r"clip\.json", r"clip\.raw", r"camera\.json", r"camera_mask\.png",
                                    r"camera_crosstalk\.npz", r"truth/frame_\d+\.exr",
                                    r"raw_png/frame_\d+\.png", r"raw_tiff/frame_\d+\.tif")


def exposure_scale(scene: np.ndarray, profile, stops: float) -> float:
    """Scene to flux factor: the scene's median lands at 18 % of the regular pixels' range, times 2^stops
    (fixed per clip, so the video does not flicker)."""
    med = float(np.median(scene[scene > 0])) if (scene > 0).any() else 1.0
    return 0.18 * profile.regular_white / med * 2.0 ** stops


FLUX_MAX = 1e30   # DN: far beyond any full well, far below float32's overflow (3.4e38)


def check_scene(scene: np.ndarray, profile, stops: float, name: str = "scene") -> float:
    """ValueError naming `name` unless `scene` can be exposed: a 2-D array (at least 2 x 2) of finite
    values whose exposure (`exposure_scale`) is a positive float32 factor that keeps its brightest pixel a
    finite float32 flux (<= FLUX_MAX); returns that factor."""
    if scene.ndim != 2 or min(scene.shape) < 2:
        raise ValueError(f"{name}: scene must be a 2-D luminance image of at least 2x2, got shape {scene.shape}")
    finite = np.isfinite(scene)
    if not finite.all():
        raise ValueError(f"{name}: {int(np.sum(~finite))} scene values are NaN or infinite")
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        k = exposure_scale(scene, profile, stops)
    peak = float(np.max(scene)) * k
    if not (math.isfinite(k) and 0 < k <= float(np.finfo(np.float32).max) and math.isfinite(peak)
            and peak <= FLUX_MAX):
        lit = scene[scene > 0]
        rng = f"{float(lit.min()):.3g}..{float(lit.max()):.3g}" if lit.size else "none"
        raise ValueError(f"{name}: the scene cannot be exposed: its positive values ({rng}) at exposure "
                         f"{stops:+g} stops give a scale factor {k:.3g} (must be in (0, 3.4e38]) and a peak flux "
                         f"{peak:.3g} DN (must be at most {FLUX_MAX:g}); rescale the scene values towards 1")
    return k


def view(scene: np.ndarray, h: int, w: int, t: float, motion: Motion, prefiltered=None) -> np.ndarray:
    """Resample the view at time t in [0, 1] (bilinear on an anti-aliased scene)."""
    from scipy.ndimage import map_coordinates
    H, W = scene.shape
    src = prefiltered if prefiltered is not None else scene
    # view size in scene pixels, keeping the output aspect ratio
    aspect = w / h
    vw = min(W, H * aspect) * motion.fov / (1.0 + (motion.zoom - 1.0) * t)
    vh = vw / aspect
    cx = W / 2 + (t - 0.5) * motion.pan * W
    cy = H / 2 + (t - 0.5) * motion.tilt * H
    cx = min(max(cx, vw / 2), W - vw / 2)
    cy = min(max(cy, vh / 2), H - vh / 2)
    ys = cy - vh / 2 + (np.arange(h) + 0.5) * vh / h - 0.5
    xs = cx - vw / 2 + (np.arange(w) + 0.5) * vw / w - 0.5
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    out = map_coordinates(src, [yy, xx], order=1, mode="nearest")
    return np.maximum(out, 0.0).astype(np.float32)


def simulate_clip(scene: np.ndarray, out_dir, profile=None, frames: int = 60, fps: int = 30,
                  exposure_stops: float = 0.0, motion: Motion = Motion(), seed: int = 0,
                  sensor_model=None, sequence: str | None = None, scene_name: str = "scene",
                  progress: bool = True, overwrite: bool = False) -> dict:
    """Simulate `frames` raw frames of `scene` (linear luminance) and write the clip folder; returns the
    clip description also written to clip.json. `sequence`: None, "png" or "tiff" (16-bit raw frames).

    The folder is written as a whole (outputs.staged_folder): a stopped run (SIGINT, SIGTERM, SIGHUP)
    removes its temporary folder and leaves an existing clip untouched, a killed run's is removed by the
    next run, a second writer of the folder is refused (outputs.OutputLockedError); a non-empty `out_dir`
    is refused (io.OutputExistsError) unless `overwrite`, which replaces only the files a clip consists of
    (CLIP_OUTPUTS) and keeps any other file there."""
    check_args(frames, fps, exposure_stops, motion, sequence)
    prof = profile if profile is not None else profiles.default()
    scene = np.asarray(scene, np.float32)
    check_scene(scene, prof, exposure_stops, scene_name)
    with outputs.staged_folder(out_dir, force=overwrite, owned=CLIP_OUTPUTS) as tmp:
        info = _write_clip(scene, tmp, prof, frames, fps, exposure_stops, motion, seed, sensor_model,
                           sequence, scene_name, progress)
    return info


def _write_clip(scene, out: Path, prof, frames, fps, exposure_stops, motion, seed, sensor_model, sequence,
                scene_name, progress) -> dict:
    from scipy.ndimage import gaussian_filter
    h, w = prof.height, prof.width
    (out / "truth").mkdir(exist_ok=True)
    profiles.save(prof, out / "camera.json")
    k = exposure_scale(scene, prof, exposure_stops)
    # anti-alias once: the view shrinks the scene by about W * fov / w
    shrink = max(scene.shape[1] * motion.fov / w, 1.0)
    pre = gaussian_filter(scene, 0.5 * math.sqrt(max(shrink ** 2 - 1, 0))) if shrink > 1.2 else scene
    rng = np.random.default_rng(seed)
    seq_dir = None
    if sequence:
        seq_dir = out / ("raw_png" if sequence == "png" else "raw_tiff")
        seq_dir.mkdir(exist_ok=True)
    it = range(frames)
    if progress:
        from tqdm import tqdm
        it = tqdm(it, desc="simulate", unit="frame")
    with io.RawVideoWriter(out / "clip.raw", w, h) as writer:
        for i in it:
            t = i / max(frames - 1, 1)
            flux = view(scene, h, w, t, motion, prefiltered=pre) * np.float32(k)
            raw = sensor.capture(flux, prof, rng, sensor_model=sensor_model)
            writer.write(raw)
            io.write_exr(out / "truth" / f"frame_{i:05d}.exr", flux)
            if seq_dir is not None:
                ext = "png" if sequence == "png" else "tif"
                io.write_image(seq_dir / f"frame_{i:05d}.{ext}", raw, np.uint16)
    info = {"format": CLIP_FORMAT, "version": 1, "width": w, "height": h, "fps": fps, "frames": frames,
            "raw": "clip.raw", "pixel_format": "GRAY16_LE", "profile": "camera.json",
            "truth": "truth/frame_%05d.exr", "scene": scene_name, "exposure_stops": exposure_stops,
            "exposure_scale": k, "seed": seed,
            "motion": {"pan": motion.pan, "tilt": motion.tilt, "zoom": motion.zoom, "fov": motion.fov},
            "sensor_model": getattr(sensor_model, "name", None) if sensor_model is not None else None,
            "sequence": sequence}
    outputs.write_text(out / "clip.json", json.dumps(info, indent=2) + "\n")
    return info


class ClipError(ValueError):
    """A clip folder or its clip.json is missing, unreadable or inconsistent; the message names the file and
    the field."""


CLIP_FILES = ("raw", "profile", "truth")      # the fields of clip.json that name files in the clip folder


def load_clip(clip_dir, allow_outside: bool = False) -> dict:
    """Read clip.json (io.read_json) and check it: format and version, positive integer size, rate and
    frame count, and the files it names (`CLIP_FILES`) inside the clip folder unless `allow_outside`
    (io.resolve_named). Adds "dir" (the folder, absolute) and "<field>_path" (absolute) for each of
    `CLIP_FILES`. Errors: ClipError naming clip.json and the field."""
    d = Path(clip_dir)
    f = d / "clip.json"
    if not f.is_file():
        raise ClipError(f"{d}: not a clip folder (no clip.json); make one with 'nrhdr simulate'")
    info = io.read_json(f, "clip description (clip.json)", error=ClipError)
    if info.get("format") != CLIP_FORMAT:
        raise ClipError(f"{f}: not an nrhdr clip description (field 'format' must be '{CLIP_FORMAT}')")
    if info.get("version") != 1 or isinstance(info.get("version"), bool):
        raise ClipError(f"{f}: field 'version': this nrhdr reads version 1, file has {info.get('version')!r}")
    for k, hi in (("width", profiles.MAX_SIZE), ("height", profiles.MAX_SIZE), ("fps", 10000), ("frames", 10 ** 9)):
        v = info.get(k)
        if not (isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= hi):
            raise ClipError(f"{f}: field '{k}' must be an integer in 1..{hi}, got {v!r}")
    if info.get("pixel_format", "GRAY16_LE") != "GRAY16_LE":
        raise ClipError(f"{f}: field 'pixel_format' must be 'GRAY16_LE', got {info.get('pixel_format')!r}")
    info.setdefault("raw", "clip.raw")
    info.setdefault("profile", "camera.json")
    for k in CLIP_FILES:
        if k in info:
            info[f"{k}_path"] = str(io.resolve_named(f, k, info[k], ClipError, allow_outside))
    info["dir"] = str(d.resolve())
    return info
