"""Scene to raw sensor video: camera motion across an HDR scene, objects moving over it and a scene cut,
captured by the sensor model, monochrome or through a Bayer colour filter array (docs/COLOUR.md).

Writes a clip folder (docs/SIMULATOR.md): `clip.raw` (GRAY16_LE, for `filesrc ! rawvideoparse`; a Bayer
mosaic for a colour sensor), `camera.json` + `camera_mask.png` (the profile), `clip.json` (size, rate, frames;
CFA, ND layout and channel sensitivity of a colour sensor), `truth/frame_%05d.exr` (noise-free, unclipped
linear DN: what a perfect chain would output; channels R, G, B in camera RGB for a colour sensor) and, on
request, `raw_png/frame_%05d.png` or `raw_tiff/frame_%05d.tif` (16-bit). Seeded and deterministic.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import cfa as cfas
from . import io, outputs, profile as profiles, sensor
from . import mask as masks

CLIP_FORMAT = "nrhdr-clip"
CLIP_VERSIONS = (1, 2)      # 1: a monochrome sensor; 2: a colour one (fields cfa, nd_layout, sensitivity)
SENSITIVITY_RANGE = (1e-3, 1e3)   # a colour channel's sensitivity (relative; white balance = its inverse)


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


OBJECT_KINDS = ("disc", "patch")
OBJECT_BRIGHT = 24.0        # a bright disc: 24 x the scene's median (beyond the regular pixels' clip at 0 stops)
OBJECT_DARK = 1.0 / 32      # a dark disc: the scene's median / 32 (below l_min x ND at 0 stops)
OBJECTS_MAX = 1000
OBJECT_SIZE_MAX = 4096.0    # pixels
OBJECT_SPEED_MAX = 10000.0  # pixels per frame
OBJECT_POSITION_MAX = 1e7   # pixels from the view's corner


@dataclass(frozen=True)
class MovingObject:
    """An object crossing the view on a straight line at constant velocity, in output pixels (pixel
    centres at integer coordinates): centre (x, y) at frame 0, (vx, vy) pixels per frame, `size` the
    diameter (disc) or side (patch). A disc is uniform at `level` times the scene's median luminance; a
    patch is a square of the scene's texture at the first view's scale, cut around `source` (fractions
    of the scene's width and height). Edges are blended by the share of the pixel the object covers;
    objects occlude the background and the objects before them."""
    kind: str = "disc"
    x: float = 0.0
    y: float = 0.0
    vx: float = 0.0
    vy: float = 0.0
    size: float = 32.0
    level: float = OBJECT_BRIGHT
    source: tuple = (0.5, 0.5)

    def centre(self, i: int) -> tuple[float, float]:
        """(x, y) of the centre in frame i."""
        return self.x + self.vx * i, self.y + self.vy * i

    def validate(self, name: str = "object") -> None:
        """ValueError naming `name` and the field: kind in OBJECT_KINDS, finite position within
        +-OBJECT_POSITION_MAX, speed within +-OBJECT_SPEED_MAX pixels per frame, size in
        1..OBJECT_SIZE_MAX, level in (0, 1e6], source two fractions in 0..1."""
        if self.kind not in OBJECT_KINDS:
            raise ValueError(f"{name}: kind must be one of {', '.join(OBJECT_KINDS)}, got {self.kind!r}")
        for k, lim in (("x", OBJECT_POSITION_MAX), ("y", OBJECT_POSITION_MAX), ("vx", OBJECT_SPEED_MAX),
                       ("vy", OBJECT_SPEED_MAX)):
            v = getattr(self, k)
            if not (_finite(v) and abs(v) <= lim):
                raise ValueError(f"{name}: {k} must be a finite number within -{lim:g}..{lim:g}, got {v!r}")
        if not (_finite(self.size) and 1 <= self.size <= OBJECT_SIZE_MAX):
            raise ValueError(f"{name}: size must be a number in 1..{OBJECT_SIZE_MAX:g} pixels, got {self.size!r}")
        if not (_finite(self.level) and 0 < self.level <= 1e6):
            raise ValueError(f"{name}: level must be in (0, 1e6] (times the scene's median), got {self.level!r}")
        src = self.source
        if not (isinstance(src, (tuple, list)) and len(src) == 2 and all(_finite(u) and 0 <= u <= 1 for u in src)):
            raise ValueError(f"{name}: source must be two fractions (u, v) in 0..1 of the scene, got {src!r}")


def _finite(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(v)


OBJECT_MIXES = OBJECT_KINDS + ("mixed",)   # `random_objects`' kinds: mixed cycles patch, bright disc, dark disc
OBJECT_STREAM = 0x6F626A                   # the objects' random stream beside the noise's: seed (seed, this)


def random_objects(count: int, height: int, width: int, frames: int, speed: float, size: float,
                   kind: str = "mixed", seed: int = 0) -> tuple[MovingObject, ...]:
    """`count` objects crossing a height x width view at `speed` pixels per frame, drawn from `seed` (a
    stream of its own: the sensor noise is the same with and without objects): a direction uniform on the
    circle, the mid-clip centre uniform in the view's central 70 %, a patch's source uniform in the
    scene's central 80 %. Discs alternate bright (OBJECT_BRIGHT) and dark (OBJECT_DARK); `mixed` cycles
    patch, bright disc, dark disc."""
    if not (isinstance(count, (int, np.integer)) and not isinstance(count, bool) and 0 <= count <= OBJECTS_MAX):
        raise ValueError(f"objects must be an integer in 0..{OBJECTS_MAX}, got {count!r}")
    if kind not in OBJECT_MIXES:
        raise ValueError(f"object kind must be one of {', '.join(OBJECT_MIXES)}, got {kind!r}")
    if not (_finite(speed) and 0 <= speed <= OBJECT_SPEED_MAX):
        raise ValueError(f"object speed must be in 0..{OBJECT_SPEED_MAX:g} pixels per frame, got {speed!r}")
    rng = np.random.default_rng((seed, OBJECT_STREAM))
    mid = (frames - 1) / 2
    out = []
    for j in range(count):
        ang = rng.uniform(0, 2 * math.pi)
        xm, ym = rng.uniform(0.15, 0.85) * width, rng.uniform(0.15, 0.85) * height
        src = (float(rng.uniform(0.1, 0.9)), float(rng.uniform(0.1, 0.9)))
        k = kind if kind != "mixed" else ("patch", "disc", "disc")[j % 3]
        nth_disc = j if kind == "disc" else j % 3 - 1
        vx, vy = speed * math.cos(ang), speed * math.sin(ang)
        o = MovingObject(kind=k, x=xm - vx * mid, y=ym - vy * mid, vx=vx, vy=vy, size=float(size),
                         level=1.0 if k == "patch" else OBJECT_BRIGHT if nth_disc % 2 == 0 else OBJECT_DARK,
                         source=src)
        o.validate(f"object {j}")
        out.append(o)
    return tuple(out)


def _coverage(lo: float, hi: float, n: int) -> np.ndarray:
    """Share of each pixel 0..n-1 (pixel c covering [c - 0.5, c + 0.5]) inside the interval [lo, hi]."""
    c = np.arange(n, dtype=np.float64)
    return np.clip(np.minimum(c + 0.5, hi) - np.maximum(c - 0.5, lo), 0.0, 1.0)


def composite(frame: np.ndarray, objects, i: int, median: float, textures) -> None:
    """Draw `objects` at their frame-i positions over `frame` (scene units, in place), in order (later
    ones in front): value = a x object + (1 - a) x below, a the covered share of the pixel (a disc's
    a = clip(r + 0.5 - d, 0, 1), d the distance of the pixel's centre; a patch's the exact area).
    `textures[j]`: patch j's texture (`patch_texture`), None for a disc."""
    from scipy.ndimage import map_coordinates
    h, w = frame.shape
    for o, tex in zip(objects, textures):
        cx, cy = o.centre(i)
        r = o.size / 2
        x0, x1 = max(int(math.floor(cx - r - 1)), 0), min(int(math.ceil(cx + r + 1)) + 1, w)
        y0, y1 = max(int(math.floor(cy - r - 1)), 0), min(int(math.ceil(cy + r + 1)) + 1, h)
        if x0 >= x1 or y0 >= y1:
            continue
        ys = np.arange(y0, y1, dtype=np.float64)[:, None]
        xs = np.arange(x0, x1, dtype=np.float64)[None, :]
        if o.kind == "disc":
            a = np.clip(r + 0.5 - np.hypot(xs - cx, ys - cy), 0.0, 1.0)
            val = np.float64(np.float32(o.level * median))
        else:
            a = _coverage(cy - r, cy + r, h)[y0:y1, None] * _coverage(cx - r, cx + r, w)[None, x0:x1]
            c = (tex.shape[0] - 1) / 2
            yy, xx = np.broadcast_arrays(ys - cy + c, xs - cx + c)
            val = map_coordinates(tex, [yy, xx], order=1, mode="nearest").astype(np.float64)
        below = frame[y0:y1, x0:x1].astype(np.float64)
        frame[y0:y1, x0:x1] = np.where(a >= 1.0, val, a * val + (1.0 - a) * below).astype(np.float32)


def patch_texture(prefiltered: np.ndarray, obj: MovingObject, scale: float) -> np.ndarray:
    """The square texture of patch `obj`: the (anti-aliased) scene around `obj.source`, resampled to
    output pixels at `scale` scene pixels per output pixel, with a 2-pixel margin (float32, odd side)."""
    from scipy.ndimage import map_coordinates
    n = 2 * (int(math.ceil(obj.size / 2)) + 2) + 1
    H, W = prefiltered.shape
    c = (n - 1) / 2
    d = (np.arange(n) - c) * scale
    yy, xx = np.meshgrid(obj.source[1] * H - 0.5 + d, obj.source[0] * W - 0.5 + d, indexing="ij")
    return np.maximum(map_coordinates(prefiltered, [yy, xx], order=1, mode="nearest"), 0.0).astype(np.float32)


EXPOSURE_STOPS_MAX = 30.0   # |exposure| beyond 30 stops is all black or all clipped on any sensor


def check_sensitivity(sensitivity, what: str = "sensitivity") -> tuple[float, float, float]:
    """`sensitivity` as three floats (R, G, B), each finite in SENSITIVITY_RANGE; ValueError naming `what`."""
    lo, hi = SENSITIVITY_RANGE
    ok = isinstance(sensitivity, (tuple, list, np.ndarray)) and len(sensitivity) == 3 and all(
        _finite(v) and lo <= v <= hi for v in sensitivity)
    if not ok:
        raise ValueError(f"{what}: must be three finite numbers (R, G, B) in {lo:g}..{hi:g}, got {sensitivity!r}")
    return tuple(float(v) for v in sensitivity)


def white_balance_of(sensitivity) -> tuple[float, float, float]:
    """The white balance (R, G, B gains) of a camera whose channels have `sensitivity`: 1 / sensitivity,
    normalised to green (a grey object then reads grey)."""
    r, g, b = check_sensitivity(sensitivity)
    return (g / r, 1.0, g / b)


def check_colour_args(cfa=None, nd_layout=None, sensitivity=None) -> None:
    """ValueError naming the argument: `cfa` one of cfa.CFAS, `nd_layout` one of mask.ND_LAYOUTS (a colour
    sensor's only), `sensitivity` three numbers (`check_sensitivity`; other than 1, 1, 1 a colour sensor's
    only). None: not given."""
    colour = cfa is not None and cfas.is_colour(cfas.check(cfa))
    if nd_layout is not None:
        masks.check_nd_layout(nd_layout)
        if cfa is not None and not colour and nd_layout != "independent":
            raise ValueError(f"nd_layout: {nd_layout!r} places the ND filter over a colour filter array; a "
                             f"monochrome sensor (cfa none) has the layout 'independent'")
    if sensitivity is not None:
        sens = check_sensitivity(sensitivity)
        if cfa is not None and not colour and sens != (1.0, 1.0, 1.0):
            raise ValueError(f"sensitivity: {sensitivity!r} weighs colour channels; a monochrome sensor (cfa "
                             f"none) has none")


def check_args(frames: int, fps: int, exposure_stops: float, motion: Motion, sequence=None, objects=(),
               cut_frame=None, cfa=None, nd_layout=None, sensitivity=None) -> None:
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
    objects = tuple(objects)
    if len(objects) > OBJECTS_MAX:
        raise ValueError(f"objects: at most {OBJECTS_MAX} moving objects, got {len(objects)}")
    for j, o in enumerate(objects):
        if not isinstance(o, MovingObject):
            raise ValueError(f"objects[{j}] must be a simulate.MovingObject, got {type(o).__name__}")
        o.validate(f"objects[{j}]")
    if cut_frame is not None and not (isinstance(cut_frame, (int, np.integer)) and not isinstance(cut_frame, bool)
                                      and 1 <= cut_frame < frames):
        raise ValueError(f"cut_frame must be an integer in 1..{frames - 1} (the first frame of the second shot, "
                         f"inside the clip's {frames} frames), got {cut_frame!r}")
    check_colour_args(cfa, nd_layout, sensitivity)


# What simulate_clip writes into a clip folder (outputs.staged_folder: with overwrite, only these are replaced).
CLIP_OUTPUTS = io.owned_by_patterns(r"clip\.json", r"clip\.raw", r"camera\.json", r"camera_mask\.png",
                                    r"camera_crosstalk\.npz", r"truth/frame_\d+\.exr",
                                    r"raw_png/frame_\d+\.png", r"raw_tiff/frame_\d+\.tif")


def exposure_scale(scene: np.ndarray, profile, stops: float) -> float:
    """Scene to flux factor: the scene's median lands at 18 % of the regular pixels' range, times 2^stops
    (fixed per clip, so the video does not flicker)."""
    return 0.18 * profile.regular_white / scene_median(scene) * 2.0 ** stops


def scene_median(scene: np.ndarray) -> float:
    """The median of the scene's positive values (1 when there is none): the exposure's and the moving
    discs' reference level."""
    return float(np.median(scene[scene > 0])) if (scene > 0).any() else 1.0


FLUX_MAX = 1e30   # DN: far beyond any full well, far below float32's overflow (3.4e38)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance (float32 (H, W)) of planar linear RGB (3, H, W), as `io.read_luminance` weighs it."""
    a = np.asarray(rgb, np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        return np.tensordot(io.LUMA_709, a, axes=1).astype(np.float32)


# Colours of the synthesised scene in colour (`tint_synthetic`): linear BT.709 RGB, each scaled to luminance 1.
# The patches: a column between the zone plate and the window (scene.synthetic_hdr_scene's layout), top to bottom.
SYNTHETIC_PATCHES = (("red", (0.80, 0.12, 0.08)), ("yellow", (0.80, 0.70, 0.10)), ("green", (0.12, 0.60, 0.12)),
                     ("cyan", (0.10, 0.60, 0.75)), ("blue", (0.10, 0.15, 0.80)), ("magenta", (0.75, 0.12, 0.65)))
SYNTHETIC_SKY = (0.80, 0.90, 1.00)          # pale blue: its blue stays within the ND pixels' range
SYNTHETIC_FLOOR = (1.00, 0.72, 0.45)        # warm wood
PATCH_COLUMN = (0.345, 0.455)               # u range of the patch column
PATCH_ROWS = (0.18, 0.07, 0.06)             # v of the first patch's top, pitch, height


def _unit_luminance(rgb) -> np.ndarray:
    c = np.asarray(rgb, np.float64)
    return c / float(io.LUMA_709 @ c)


def synthetic_chroma(height: int, width: int) -> np.ndarray:
    """The colour of every pixel of `tint_synthetic` (float64 (3, H, W), Rec. 709 luminance 1): grey (1, 1, 1)
    except the patch column (`SYNTHETIC_PATCHES`), the window (`SYNTHETIC_SKY`, where the sky is bright) and
    the floor band (`SYNTHETIC_FLOOR`), placed in `scene.synthetic_hdr_scene`'s layout (fractions of the size)."""
    v = (np.arange(height) + 0.5)[:, None] / height
    u = (np.arange(width) + 0.5)[None, :] / width
    chroma = np.ones((3, height, width))
    floor = np.clip((v - 0.80) / 0.03, 0.0, 1.0)[None]                       # the shadowed floor band
    chroma += floor * (_unit_luminance(SYNTHETIC_FLOOR)[:, None, None] - 1.0)
    cols = (u >= PATCH_COLUMN[0]) & (u < PATCH_COLUMN[1])
    top, pitch, size = PATCH_ROWS
    for k, (_name, rgb) in enumerate(SYNTHETIC_PATCHES):
        patch = cols & (v >= top + k * pitch) & (v < top + k * pitch + size)
        chroma[:, patch] = _unit_luminance(rgb)[:, None]
    return chroma


def tint_synthetic(lum: np.ndarray) -> np.ndarray:
    """Planar linear RGB (float32 (3, H, W)) of the synthesised luminance scene `lum` (scene.synthetic_hdr_scene
    of any size): `synthetic_chroma` x `lum`, so its Rec. 709 luminance is `lum` (to float32 rounding); the
    window's bright sky (above 3, scene units) is `SYNTHETIC_SKY`, its branches and frame stay grey.
    Deterministic; the zone plate, the walls, the shadow and the lamp are grey."""
    lum = np.asarray(lum, np.float32)
    if lum.ndim != 2:
        raise ValueError(f"tint_synthetic: a luminance image (H, W) is needed, got shape {lum.shape}")
    h, w = lum.shape
    chroma = synthetic_chroma(h, w)
    v = (np.arange(h) + 0.5)[:, None] / h
    u = (np.arange(w) + 0.5)[None, :] / w
    sky = (u >= 0.48) & (u < 0.92) & (v >= 0.12) & (v < 0.62) & (lum > 3.0)
    chroma[:, sky] = _unit_luminance(SYNTHETIC_SKY)[:, None]
    return np.ascontiguousarray((chroma * lum[None]).astype(np.float32))


def synthetic_rgb_scene(height: int = 1200, width: int = 1600, seed: int = 7, cached: bool = False) -> np.ndarray:
    """The synthesised HDR scene in colour: `tint_synthetic` of `scene.synthetic_hdr_scene` (through its file
    cache, `scene.cached_synthetic_hdr_scene`, when `cached`)."""
    from . import scene
    make = scene.cached_synthetic_hdr_scene if cached else scene.synthetic_hdr_scene
    return tint_synthetic(make(height, width, seed))


def is_rgb_scene(scene) -> bool:
    """True for a planar colour scene (3, H, W), False for a luminance scene (H, W)."""
    return np.ndim(scene) == 3 and np.shape(scene)[0] == 3


def check_scene(scene: np.ndarray, profile, stops: float, name: str = "scene", sensitivity=(1.0, 1.0, 1.0)) -> float:
    """ValueError naming `name` unless `scene` can be exposed: a 2-D luminance array or planar RGB (3, H, W)
    (at least 2 x 2) of finite values whose exposure (`exposure_scale` of its luminance) is a positive
    float32 factor that keeps its brightest value (times the largest channel `sensitivity`, for RGB) a finite
    float32 flux (<= FLUX_MAX); returns that factor."""
    scene = np.asarray(scene)
    rgb = is_rgb_scene(scene)
    if not (scene.ndim == 2 or rgb) or min(scene.shape[-2:]) < 2:
        raise ValueError(f"{name}: scene must be a 2-D luminance image or planar RGB (3, H, W) of at least 2x2, "
                         f"got shape {scene.shape}")
    finite = np.isfinite(scene)
    if not finite.all():
        raise ValueError(f"{name}: {int(np.sum(~finite))} scene values are NaN or infinite")
    lum = luminance(scene) if rgb else scene
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        k = exposure_scale(lum, profile, stops)
    peak = float(np.max(scene)) * k * (max(check_sensitivity(sensitivity)) if rgb else 1.0)
    if not (math.isfinite(k) and 0 < k <= float(np.finfo(np.float32).max) and math.isfinite(peak)
            and peak <= FLUX_MAX):
        lit = lum[lum > 0]
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


def prefilter(scene: np.ndarray, width: int, motion: Motion) -> np.ndarray:
    """The anti-aliased scene the views sample: a Gaussian for the view's shrink of about W x fov / width."""
    from scipy.ndimage import gaussian_filter
    shrink = max(scene.shape[1] * motion.fov / width, 1.0)
    return gaussian_filter(scene, 0.5 * math.sqrt(max(shrink ** 2 - 1, 0))) if shrink > 1.2 else scene


class ClipRenderer:
    """The noise-free flux (float32 DN, the profile's size) of frame i of a clip, what `simulate_clip`
    writes as its truth: the view of `scene` along `motion` at t = i / (frames - 1) times the exposure
    factor (`exposure_scale`), with `objects` (MovingObject) drawn over it (`composite`); from frame
    `cut_frame` on, the second shot: the view of `cut_scene` (default: `scene` turned by 180 degrees, a
    far region upside down) along the same path, exposed for that scene, without the objects.

    A colour sensor (`profile.cfa` a Bayer phase, docs/COLOUR.md): `scene` is planar linear RGB (3, H, W) (a
    luminance scene is grey); each channel is viewed along the same path, objects and cut alike (a disc is
    grey at its level), the exposure factor comes from the luminance, and channel c's flux is its view x the
    exposure factor x `sensitivity[c]` (camera RGB, not white balanced). A monochrome sensor views the
    luminance of an RGB scene."""

    def __init__(self, scene: np.ndarray, profile, frames: int, exposure_stops: float = 0.0,
                 motion: Motion = Motion(), objects=(), cut_frame: int | None = None, cut_scene=None,
                 cut_scene_name: str | None = None, sensitivity=(1.0, 1.0, 1.0)):
        self.h, self.w = profile.height, profile.width
        self.frames, self.motion = frames, motion
        self.objects = tuple(objects)
        self.cfa = profile.cfa
        self.colour = cfas.is_colour(profile.cfa)
        self.sensitivity = check_sensitivity(sensitivity)
        if not self.colour and self.sensitivity != (1.0, 1.0, 1.0):
            raise ValueError(f"sensitivity: {sensitivity!r} weighs colour channels; the profile's sensor is "
                             f"monochrome (cfa none)")
        self.scene = self._planes(scene)
        lum = luminance(self.scene) if self.colour else self.scene
        self.scale = exposure_scale(lum, profile, exposure_stops)
        self._pre = self._prefilter(self.scene)
        self.cut_frame = cut_frame
        if cut_frame is not None:
            self.cut_scene = (np.ascontiguousarray(np.rot90(self.scene, 2, axes=(-2, -1))) if cut_scene is None
                              else self._planes(cut_scene))
            self.cut_scale = exposure_scale(luminance(self.cut_scene) if self.colour else self.cut_scene,
                                            profile, exposure_stops)
            self.cut_name = cut_scene_name or ("the scene turned by 180 degrees" if cut_scene is None
                                               else "cut scene")
            self._cut_pre = self._prefilter(self.cut_scene)
        if self.objects:
            self.median = scene_median(lum)
            H, W = self.scene.shape[-2:]
            px = min(W, H * self.w / self.h) * motion.fov / self.w     # scene pixels per output pixel at t = 0
            planes = self._pre if self.colour else [self._pre]
            self._tex = [[patch_texture(pre, o, px) if o.kind == "patch" else None for o in self.objects]
                         for pre in planes]

    def _planes(self, scene) -> np.ndarray:
        """The scene as this sensor sees it: (3, H, W) for colour (a luminance scene grey), (H, W) else."""
        a = np.asarray(scene, np.float32)
        if self.colour:
            return np.ascontiguousarray(a if is_rgb_scene(a) else np.broadcast_to(a, (3,) + a.shape))
        return luminance(a) if is_rgb_scene(a) else a

    def _prefilter(self, scene):
        return [prefilter(c, self.w, self.motion) for c in scene] if self.colour else \
            prefilter(scene, self.w, self.motion)

    def _view(self, scene, pre, t, objects_at=None):
        if not self.colour:
            v = view(scene, self.h, self.w, t, self.motion, prefiltered=pre)
            if objects_at is not None:
                composite(v, self.objects, objects_at, self.median, self._tex[0])
            return v
        out = np.empty((3, self.h, self.w), np.float32)
        for c in range(3):
            out[c] = view(scene[c], self.h, self.w, t, self.motion, prefiltered=pre[c])
            if objects_at is not None:
                composite(out[c], self.objects, objects_at, self.median, self._tex[c])
        return out

    def _expose(self, v: np.ndarray, scale: float) -> np.ndarray:
        if not self.colour:
            return v * np.float32(scale)
        return v * np.array([scale * s for s in self.sensitivity], np.float32)[:, None, None]

    def flux(self, i: int) -> np.ndarray:
        """Frame i's noise-free flux (float32 DN): (H, W), or camera RGB (3, H, W) for a colour sensor."""
        t = i / max(self.frames - 1, 1)
        if self.cut_frame is not None and i >= self.cut_frame:
            return self._expose(self._view(self.cut_scene, self._cut_pre, t), self.cut_scale)
        return self._expose(self._view(self.scene, self._pre, t, i if self.objects else None), self.scale)

    def photosite_flux(self, flux: np.ndarray) -> np.ndarray:
        """The flux each photosite receives (float32 (H, W), `sensor.capture`'s input) of a frame's `flux`:
        itself for a monochrome sensor, the CFA mosaic (`cfa.mosaic`) of the camera RGB for a colour one."""
        return cfas.mosaic(flux, self.cfa) if self.colour else flux


def simulate_clip(scene: np.ndarray, out_dir, profile=None, frames: int = 60, fps: int = 30,
                  exposure_stops: float = 0.0, motion: Motion = Motion(), seed: int = 0,
                  sensor_model=None, sequence: str | None = None, scene_name: str = "scene",
                  progress: bool = True, overwrite: bool = False, objects=(), cut_frame: int | None = None,
                  cut_scene=None, cut_scene_name: str | None = None, cfa: str | None = None,
                  nd_layout: str | None = None, sensitivity=None) -> dict:
    """Simulate `frames` raw frames of `scene` (linear luminance (H, W) or planar linear RGB (3, H, W)) and
    write the clip folder; returns the clip description also written to clip.json. `sequence`: None, "png"
    or "tiff" (16-bit raw frames). `objects` (MovingObject, e.g. from `random_objects`) move over the view;
    `cut_frame` starts a second shot of `cut_scene` (None: `scene` turned by 180 degrees), see
    `ClipRenderer`. Without objects and cut the frames do not depend on these arguments.

    Colour (docs/COLOUR.md): `cfa` (cfa.CFAS; None: the profile's, or none without a profile) a Bayer phase
    simulates a colour sensor: each photosite's flux is its CFA channel of the camera RGB flux (`ClipRenderer`,
    `sensitivity` (R, G, B), default 1, 1, 1), captured by `sensor.capture` unchanged; the truth is the camera
    RGB flux (3-channel EXR). Without `profile`, `profiles.default` makes one in ND layout `nd_layout`
    (mask.ND_LAYOUTS, default mask.DEFAULT_ND_LAYOUT); with one, its mask must fit `nd_layout` when given
    (`mask.nd_layout_of`) and its cfa must be `cfa`. The profile written has white_balance =
    `white_balance_of(sensitivity)`; clip.json (version 2) records cfa, nd_layout and sensitivity. A
    monochrome clip is written as without these arguments.

    The folder is written as a whole (outputs.staged_folder): a stopped run (SIGINT, SIGTERM, SIGHUP)
    removes its temporary folder and leaves an existing clip untouched, a killed run's is removed by the
    next run, a second writer of the folder is refused (outputs.OutputLockedError); a non-empty `out_dir`
    is refused (io.OutputExistsError) unless `overwrite`, which replaces only the files a clip consists of
    (CLIP_OUTPUTS) and keeps any other file there."""
    check_args(frames, fps, exposure_stops, motion, sequence, objects, cut_frame, cfa, nd_layout, sensitivity)
    prof, layout = clip_profile(profile, cfa, nd_layout)
    colour = cfas.is_colour(prof.cfa)
    sens = check_sensitivity(sensitivity) if sensitivity is not None else (1.0, 1.0, 1.0)
    if not colour and sens != (1.0, 1.0, 1.0):
        raise ValueError(f"sensitivity: {sensitivity!r} weighs colour channels; the sensor is monochrome (cfa none)")
    scene = np.asarray(scene, np.float32)
    check_scene(scene, prof, exposure_stops, scene_name, sens)
    if cut_scene is not None:
        if cut_frame is None:
            raise ValueError("cut_scene is given but cut_frame is not: say at which frame the second shot starts")
        cut_scene = np.asarray(cut_scene, np.float32)
        check_scene(cut_scene, prof, exposure_stops, cut_scene_name or "cut scene", sens)
    render = ClipRenderer(scene, prof, frames, exposure_stops, motion, objects, cut_frame, cut_scene,
                          cut_scene_name, sensitivity=sens)
    colour_info = None
    if colour:
        prof = prof.replace(white_balance=white_balance_of(sens))
        colour_info = {"cfa": prof.cfa, "nd_layout": layout, "sensitivity": list(sens)}
    with outputs.staged_folder(out_dir, force=overwrite, owned=CLIP_OUTPUTS) as tmp:
        info = _write_clip(render, tmp, prof, fps, exposure_stops, seed, sensor_model, sequence, scene_name,
                           progress, colour_info)
    return info


def clip_profile(profile, cfa, nd_layout):
    """(profile, its ND layout name) as `simulate_clip` uses them: the given `profile` checked against `cfa`
    and `nd_layout` (ValueError naming the argument), or `profiles.default` in them."""
    if profile is None:
        name = cfas.check(cfa) if cfa is not None else cfas.NONE
        fields = {"cfa": name} if cfas.is_colour(name) else {}
        prof = profiles.default(nd_layout=nd_layout, **fields)
        if cfas.is_colour(name):
            return prof, nd_layout or masks.DEFAULT_ND_LAYOUT
        return prof, "independent"
    if cfa is not None and cfas.check(cfa) != profile.cfa:
        raise ValueError(f"cfa: the profile's sensor has the CFA {profile.cfa!r}, got cfa={cfa!r}")
    found = masks.nd_layout_of(profile.mask, profile.cfa)
    if nd_layout is not None:
        fits = (found in (nd_layout, masks.NO_ND) or nd_layout == "independent"
                or (nd_layout == "balanced" and found == "regular"))
        if not fits:
            raise ValueError(f"nd_layout: the profile's mask is not in the {nd_layout!r} layout (it is "
                             f"{found!r}, mask.nd_layout_of)")
        if found != masks.NO_ND:
            found = nd_layout
    return profile, found


def _write_clip(render: ClipRenderer, out: Path, prof, fps, exposure_stops, seed, sensor_model, sequence,
                scene_name, progress, colour_info=None) -> dict:
    h, w, frames, motion = prof.height, prof.width, render.frames, render.motion
    (out / "truth").mkdir(exist_ok=True)
    profiles.save(prof, out / "camera.json")
    k = render.scale
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
            flux = render.flux(i)
            raw = sensor.capture(render.photosite_flux(flux), prof, rng, sensor_model=sensor_model)
            writer.write(raw)
            io.write_exr(out / "truth" / f"frame_{i:05d}.exr", flux)
            if seq_dir is not None:
                ext = "png" if sequence == "png" else "tif"
                io.write_image(seq_dir / f"frame_{i:05d}.{ext}", raw, np.uint16)
    info = {"format": CLIP_FORMAT, "version": 2 if colour_info else 1, "width": w, "height": h, "fps": fps,
            "frames": frames, "raw": "clip.raw", "pixel_format": "GRAY16_LE", "profile": "camera.json",
            "truth": "truth/frame_%05d.exr", **(colour_info or {}), "scene": scene_name,
            "exposure_stops": exposure_stops, "exposure_scale": k, "seed": seed,
            "motion": {"pan": motion.pan, "tilt": motion.tilt, "zoom": motion.zoom, "fov": motion.fov},
            "sensor_model": getattr(sensor_model, "name", None) if sensor_model is not None else None,
            "sequence": sequence}
    if render.objects:
        info["objects"] = [{**dataclasses.asdict(o), "source": list(o.source)} for o in render.objects]
    if render.cut_frame is not None:
        info["cut"] = {"frame": int(render.cut_frame), "scene": render.cut_name,
                       "exposure_scale": render.cut_scale}
    outputs.write_text(out / "clip.json", json.dumps(info, indent=2) + "\n")
    return info


class ClipError(ValueError):
    """A clip folder or its clip.json is missing, unreadable or inconsistent; the message names the file and
    the field."""


CLIP_FILES = ("raw", "profile", "truth")      # the fields of clip.json that name files in the clip folder


def load_clip(clip_dir, allow_outside: bool = False) -> dict:
    """Read clip.json (io.read_json) and check it: format and version, positive integer size, rate and
    frame count, and the files it names (`CLIP_FILES`) inside the clip folder unless `allow_outside`
    (io.resolve_named). A colour clip (version 2): `cfa` a Bayer phase with an even width and height,
    `nd_layout` one of mask.ND_LAYOUTS or none, `sensitivity` three numbers (`check_sensitivity`); the
    profile's `cfa` (camera.json) and the first truth frame's channels (3 for colour, 1 else) must agree.
    Adds "dir" (the folder, absolute), "<field>_path" (absolute) for each of `CLIP_FILES`, "cfa" (none for
    a monochrome clip) and "channels" (of the truth: 1 or 3). Errors: ClipError naming the file and the
    field."""
    d = Path(clip_dir)
    f = d / "clip.json"
    if not f.is_file():
        raise ClipError(f"{d}: not a clip folder (no clip.json); make one with 'nrhdr simulate'")
    info = io.read_json(f, "clip description (clip.json)", error=ClipError)
    if info.get("format") != CLIP_FORMAT:
        raise ClipError(f"{f}: not an nrhdr clip description (field 'format' must be '{CLIP_FORMAT}')")
    if info.get("version") not in CLIP_VERSIONS or isinstance(info.get("version"), bool):
        raise ClipError(f"{f}: field 'version': this nrhdr reads versions "
                        f"{', '.join(map(str, CLIP_VERSIONS))}, file has {info.get('version')!r}")
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
    _check_clip_colour(f, info)
    info["dir"] = str(d.resolve())
    if "truth" in info:
        first = _truth_file(f, info, 0, allow_outside)
        if first.is_file():
            _check_truth_channels(f, info, first)
    return info


COLOUR_FIELDS = ("cfa", "nd_layout", "sensitivity")     # clip.json fields of a colour clip (version 2)


def _check_clip_colour(f: Path, info: dict) -> None:
    """The colour fields of clip.json `f` (COLOUR_FIELDS), in place: "cfa" and "channels" set."""
    cfa = info.get("cfa", cfas.NONE)
    if not isinstance(cfa, str) or cfa not in cfas.CFAS:
        raise ClipError(f"{f}: field 'cfa' must be one of {', '.join(cfas.CFAS)}, got {cfa!r}")
    colour = cfas.is_colour(cfa)
    if not colour:
        if info["version"] != 1:
            raise ClipError(f"{f}: field 'version': version {info['version']} describes a colour clip, but field "
                            f"'cfa' says {cfa!r} (a monochrome clip is version 1)")
        extra = [k for k in COLOUR_FIELDS[1:] if k in info]
        if extra:
            raise ClipError(f"{f}: field '{extra[0]}' belongs to a colour clip, but field 'cfa' says "
                            f"{cfa!r} (monochrome)")
    else:
        if info["version"] < 2:
            raise ClipError(f"{f}: field 'version': a colour clip (cfa {cfa!r}) is version 2 (a version-1 "
                            f"reader would read its Bayer mosaic as grey), file has {info['version']!r}")
        for k in ("width", "height"):
            if info[k] % 2:
                raise ClipError(f"{f}: field '{k}': a Bayer sensor (cfa {cfa!r}) has an even width and height, "
                                f"got {info[k]}")
        layout = info.get("nd_layout")
        if layout not in masks.ND_LAYOUTS + (masks.NO_ND,):
            raise ClipError(f"{f}: field 'nd_layout' must be one of {', '.join(masks.ND_LAYOUTS + (masks.NO_ND,))}, "
                            f"got {layout!r}")
        try:
            info["sensitivity"] = list(check_sensitivity(info.get("sensitivity"), "'sensitivity'"))
        except ValueError as e:
            raise ClipError(f"{f}: field {e}") from None
    info["cfa"] = cfa
    info["channels"] = 3 if colour else 1
    prof_path = Path(info["profile_path"])
    if prof_path.is_file():          # the profile's own errors are profile.load's to report
        try:
            pcfa = io.read_json(prof_path, "camera profile").get("cfa", cfas.NONE)
        except io.FileContentError:
            return
        if pcfa != cfa:
            raise ClipError(f"{f}: field 'cfa' is {cfa!r} but the clip's profile {prof_path} says cfa "
                            f"{pcfa!r}")


def _truth_file(f: Path, info: dict, i: int, allow_outside: bool = False) -> Path:
    """Truth frame i's file: clip.json's `truth` pattern (one %d conversion) filled with i, in the folder."""
    pattern = info.get("truth")
    try:
        name = pattern % i if isinstance(pattern, str) else None
    except (TypeError, ValueError):
        name = None
    if name is None or name == pattern:
        raise ClipError(f"{f}: field 'truth' must be a file pattern with one %d conversion (truth/"
                        f"frame_%05d.exr), got {pattern!r}")
    return io.resolve_named(f, "truth", name, ClipError, allow_outside)


def _check_truth_channels(f: Path, info: dict, path: Path) -> None:
    try:
        n = io.exr_channels(path)
    except io.ImageFileError as e:
        raise ClipError(f"{e} (a truth frame named by field 'truth' of {f})") from None
    if n != info["channels"]:
        raise ClipError(f"{path}: a truth frame of {n} channel(s), but {f} field 'cfa' is {info['cfa']!r} "
                        f"({info['channels']} channel(s): {'R, G, B' if info['channels'] == 3 else 'Y'})")


def read_truth(clip: dict, i: int, allow_outside: bool = False) -> np.ndarray:
    """Truth frame i of a clip loaded by `load_clip`: float32 (H, W), or camera RGB (3, H, W) for a colour
    clip (docs/SIMULATOR.md). Errors name the file: ClipError when its channels or size contradict
    clip.json, io.ImageFileError when it cannot be read."""
    f = Path(clip["dir"]) / "clip.json"
    if not (isinstance(i, (int, np.integer)) and 0 <= i < clip["frames"]):
        raise ValueError(f"{f}: truth frame {i!r} out of range 0..{clip['frames'] - 1}")
    path = _truth_file(f, clip, int(i), allow_outside)
    _check_truth_channels(f, clip, path)
    try:
        values, _ = io.read_exr(path, shape=(clip["height"], clip["width"]))
    except io.ImageSizeError as e:
        raise ClipError(f"{e} (the size {f} states)") from None
    return values
