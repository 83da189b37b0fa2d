"""Scene to raw sensor video: camera motion across an HDR scene, captured by the sensor model.

Writes a clip folder (docs/SIMULATOR.md): `clip.raw` (GRAY16_LE, for `filesrc ! rawvideoparse`),
`camera.json` + `camera_mask.png` (the profile), `clip.json` (size, rate, frames), `truth/frame_%05d.exr`
(noise-free, unclipped linear DN: what a perfect chain would output) and, on request,
`raw_png/frame_%05d.png` or `raw_tiff/frame_%05d.tif` (16-bit). Seeded and deterministic.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import io, profile as profiles, sensor

CLIP_FORMAT = "nrhdr-clip"


@dataclass(frozen=True)
class Motion:
    """Camera path: the view's centre moves by `pan` (fraction of the scene width) left to right and
    the view zooms by `zoom` (1 = none) over the clip; `fov` is the first view's share of the scene."""
    pan: float = 0.15
    tilt: float = 0.05
    zoom: float = 1.25
    fov: float = 0.8


def exposure_scale(scene: np.ndarray, profile, stops: float) -> float:
    """Scene to flux factor: the scene's median lands at 18 % of the regular pixels' range, times 2^stops
    (fixed per clip, so the video does not flicker)."""
    med = float(np.median(scene[scene > 0])) if (scene > 0).any() else 1.0
    return 0.18 * profile.regular_white / med * 2.0 ** stops


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
                  progress: bool = True) -> dict:
    """Simulate `frames` raw frames of `scene` (linear luminance) and write the clip folder; returns the
    clip description also written to clip.json. `sequence`: None, "png" or "tiff" (16-bit raw frames)."""
    from scipy.ndimage import gaussian_filter
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    if fps < 1:
        raise ValueError(f"fps must be >= 1, got {fps}")
    if sequence not in (None, "png", "tiff"):
        raise ValueError(f"sequence must be 'png' or 'tiff', got {sequence!r}")
    scene = np.asarray(scene, np.float32)
    if scene.ndim != 2 or min(scene.shape) < 2:
        raise ValueError(f"scene must be a 2-D luminance image, got shape {scene.shape}")
    prof = profile if profile is not None else profiles.default()
    h, w = prof.height, prof.width
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
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
    tmp = out / ".clip.json.tmp"
    tmp.write_text(json.dumps(info, indent=2) + "\n")
    os.replace(tmp, out / "clip.json")
    return info


def load_clip(clip_dir) -> dict:
    """Read clip.json with clear errors; adds absolute paths."""
    d = Path(clip_dir)
    f = d / "clip.json"
    if not f.is_file():
        raise FileNotFoundError(f"{d}: not a clip folder (no clip.json); make one with 'nrhdr simulate'")
    info = json.loads(f.read_text())
    if info.get("format") != CLIP_FORMAT:
        raise ValueError(f"{f}: not an nrhdr clip description")
    info["dir"] = str(d.resolve())
    return info
