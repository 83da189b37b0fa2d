"""A synthesised HDR test scene, so the demo needs no external data.

An interior at mid-grey with textured walls, a deep shadow, a zone plate (fine detail that regular
sub-sampling aliases, paper 2.1), a window onto a bright sky 3-4 stops above the regular pixels' clipping
(recoverable through the ND pixels) crossed by dark branches (strong edges), and a lamp far beyond even the
ND pixels' range. About 17 stops from the shadow to the lamp. Deterministic for a given seed.

`colour_zone_plate`: the colour chain's false-colour test scene (linear RGB, docs/COLOUR.md "Measured").
"""
from __future__ import annotations

import numpy as np


def _value_noise(h, w, rng, octaves=5, base=8):
    from scipy.ndimage import zoom
    acc = np.zeros((h, w))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cells = base * 2 ** o
        g = rng.random((cells + 1, int(cells * w / h) + 1))
        up = zoom(g, (h / g.shape[0], w / g.shape[1]), order=3)[:h, :w]
        acc += amp * up
        total += amp
        amp *= 0.55
    return acc / total


def synthetic_hdr_scene(height: int = 1200, width: int = 1600, seed: int = 7) -> np.ndarray:
    """Linear relative luminance (float32, H x W), median near 0.5."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    u, v = xx / width, yy / height
    # wall: soft gradient with texture
    lum = (0.35 + 0.45 * u) * (0.75 + 0.5 * _value_noise(height, width, rng))
    # floor shadow (bottom band), deep corner
    shadow = np.clip((v - 0.78) / 0.05, 0, 1)
    lum *= 1.0 - 0.9 * shadow
    corner = np.exp(-(((u - 0.0) / 0.18) ** 2 + ((v - 1.0) / 0.2) ** 2))
    lum *= 1.0 - 0.95 * corner
    # zone plate patch at mid-grey
    cx, cy, r = 0.22 * width, 0.35 * height, 0.14 * height
    rr2 = (xx - cx) ** 2 + (yy - cy) ** 2
    zp = 0.5 + 0.5 * np.cos(np.pi * rr2 / (4.4 * r))
    inside = rr2 < r * r
    lum = np.where(inside, 0.15 + 0.7 * zp, lum)
    # window: sky at 6-16x mid-grey with clouds, branches across it, frame around it
    x0, x1, y0, y1 = 0.48 * width, 0.92 * width, 0.12 * height, 0.62 * height
    win = (xx >= x0) & (xx < x1) & (yy >= y0) & (yy < y1)
    sky = 6.0 + 10.0 * (1 - (yy - y0) / (y1 - y0)) * (0.3 + 0.7 * _value_noise(height, width, rng, 4, 4))
    branches = np.zeros_like(lum, dtype=bool)
    for _ in range(9):
        ax, ay = rng.uniform(x0, x1), y1
        ang = rng.uniform(-2.2, -0.9)
        L = rng.uniform(0.3, 0.8) * (y1 - y0)
        thick = rng.uniform(2.0, 7.0)
        bx, by = ax + L * np.cos(ang), ay + L * np.sin(ang)
        # distance from segment
        dx, dy = bx - ax, by - ay
        t = np.clip(((xx - ax) * dx + (yy - ay) * dy) / (dx * dx + dy * dy), 0, 1)
        d = np.hypot(xx - (ax + t * dx), yy - (ay + t * dy))
        branches |= d < thick * (1.2 - t)
    sky = np.where(branches, 1.2, sky)
    lum = np.where(win, sky, lum)
    frame = ((np.abs(xx - x0) < 10) | (np.abs(xx - x1) < 10)) & (yy > y0 - 10) & (yy < y1 + 10)
    frame |= ((np.abs(yy - y0) < 10) | (np.abs(yy - y1) < 10)) & (xx > x0 - 10) & (xx < x1 + 10)
    lum = np.where(frame, 0.12, lum)
    # lamp: a hot core far beyond the ND pixels' range with a 1/r^2 glow
    lx, ly = 0.3 * width, 0.72 * height
    d2 = ((xx - lx) ** 2 + (yy - ly) ** 2) / (0.006 * width) ** 2
    lum = lum + 20000.0 / (1.0 + d2 ** 2)
    return lum.astype(np.float32)


def cached_synthetic_hdr_scene(height: int = 1200, width: int = 1600, seed: int = 7, cache_dir=None) -> np.ndarray:
    """`synthetic_hdr_scene` through a file cache (`cache_dir`, default $XDG_CACHE_HOME/nrhdr/scenes), keyed on
    the size, the seed and this module's source, so a live source (nrcamsrc scene=synthetic) starts in
    milliseconds once the scene was made (`nrhdr warmup` makes the 1080p one). The file is written atomically
    and checked when read (shape, dtype, finite); any problem with it means synthesising again."""
    import hashlib
    import os
    import tempfile
    from pathlib import Path
    if cache_dir is None:
        cache_dir = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "nrhdr" / "scenes"
    key = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:16]
    path = Path(cache_dir) / f"synthetic-{height}x{width}-seed{seed}-{key}.npy"
    try:
        a = np.load(path, allow_pickle=False)
        if a.shape == (height, width) and a.dtype == np.float32 and np.isfinite(a).all():
            return a
    except (OSError, ValueError):
        pass
    a = synthetic_hdr_scene(height, width, seed)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".npy.nrtmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                np.save(f, a, allow_pickle=False)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    except OSError:
        pass                        # a read-only cache: synthesise each time
    return a


ZONE_PLATE_PANELS = ("mid", "bright", "colour")


def colour_zone_plate(size: int = 256, mid: float = 0.25, bright: float = 3.0, stops: float = 1.0,
                      saturation: float = 0.5) -> tuple[np.ndarray, dict]:
    """A colour zone plate test scene in HDR: linear RGB (float32 (3, size, 3 * size)) and its panels.

    Three square panels side by side, each a circular zone plate whose local frequency grows linearly from
    0 at the centre to 0.5 cycles/pixel (the full grid's Nyquist limit) at the inscribed circle (phase
    pi r^2 / size; flat at the mean level outside it), modulated +-`stops` around a mean level in
    log2 (the rings span 2 x `stops` stops):

    - 'mid': achromatic (R = G = B) around `mid`;
    - 'bright': achromatic around `bright` (in units of the regular pixels' clip: at 3 with 1 stop every
      regular pixel of the rings clips and only ND pixels measure them);
    - 'colour': the same rings around `mid`, R and B in antiphase (R x (1 + s c), B x (1 - s c), c the
      ring signal, s = `saturation`): chromatic detail.

    A Bayer CFA samples R and B at half the grid's rate in each direction (Nyquist 0.25 cycles/pixel), an ND
    layout thins the samples of each colour further; rings beyond the rate a layout keeps alias, and aliased
    luminance detail comes back as colour that is not in the scene: false colour (`metrics.false_colour`,
    zero on the achromatic truth). Values are relative: multiply by the regular pixels' white (DN) for
    flux. Returns (rgb, {panel: bool (size, 3 * size) mask of its rings})."""
    if size < 8:
        raise ValueError(f"colour_zone_plate: size must be >= 8, got {size}")
    if not (mid > 0 and bright > 0 and stops >= 0 and 0 <= saturation < 1):
        raise ValueError("colour_zone_plate: mid and bright must be > 0, stops >= 0, saturation in [0, 1)")
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    c = (size - 1) / 2.0
    r2 = (yy - c) ** 2 + (xx - c) ** 2
    rings = r2 <= (size / 2.0) ** 2
    wave = np.where(rings, np.cos(np.pi * r2 / size), 0.0)       # d(phase)/dr / 2 pi = r / size
    level = 2.0 ** (stops * wave)
    rgb = np.empty((3, size, 3 * size), np.float64)
    rgb[:, :, :size] = mid * level
    rgb[:, :, size:2 * size] = bright * level
    col = mid * level
    rgb[0, :, 2 * size:] = col * (1.0 + saturation * wave)
    rgb[1, :, 2 * size:] = col
    rgb[2, :, 2 * size:] = col * (1.0 - saturation * wave)
    masks = {}
    for i, name in enumerate(ZONE_PLATE_PANELS):
        m = np.zeros((size, 3 * size), bool)
        m[:, i * size:(i + 1) * size] = rings
        masks[name] = m
    return rgb.astype(np.float32), masks
