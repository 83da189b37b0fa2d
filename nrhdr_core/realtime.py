"""Live operation without GStreamer: processing-time estimates for the LATENCY query, the `method=auto`
controller of nrreconstruct, the frame sources of `nrcamsrc` and a report of numba compilations.

- `FrameTimes`: running high-percentile estimate of per-frame processing time (what an element adds to the
  pipeline latency, GStreamer design doc "latency"), and whether it grew enough to announce.
- `AutoController`: per frame, the most accurate rung of `LADDER` predicted to fit a time budget, from
  measured per-rung costs scaled by the frame's missing share, with hysteresis (down at once when over
  budget, up only after `up_after` comfortable frames) so quality does not flicker.
- `ClipCamera` / `SceneCamera`: raw GRAY16 frames of a clip folder (`nrhdr simulate`) or rendered from an
  HDR scene with the simulator's camera path, moving objects, cut and sensor noise model
  (`simulate.ClipRenderer`, `sensor.capture`); a Bayer mosaic for a colour profile (docs/COLOUR.md).
- `JitWatch`: counts numba compilations (cache misses) so elements can report them instead of stalling
  silently.
"""
from __future__ import annotations

import collections
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

# ---- processing time -------------------------------------------------------------------------------


class FrameTimes:
    """Per-frame processing times of one element: `estimate()` is the `quantile` of the last `window`
    frames times `margin` (the first `skip` frames, which may include cache loading, are ignored).
    `add()` returns True when the estimate grew by more than `grow` (relative) and `floor` seconds over
    the value last announced, i.e. when the element should post a LATENCY message."""

    def __init__(self, window: int = 32, quantile: float = 0.95, margin: float = 1.2, skip: int = 1,
                 grow: float = 0.25, floor: float = 0.002):
        if not 0 < quantile <= 1:
            raise ValueError(f"quantile must be in (0, 1], got {quantile}")
        self.window, self.quantile, self.margin, self.skip = int(window), quantile, margin, int(skip)
        self.grow, self.floor = grow, floor
        self._times: collections.deque = collections.deque(maxlen=self.window)
        self._seen = 0
        self.announced = 0.0
        self._lock = threading.Lock()

    def add(self, seconds: float) -> bool:
        with self._lock:
            self._seen += 1
            if self._seen <= self.skip or not math.isfinite(seconds) or seconds < 0:
                return False
            self._times.append(float(seconds))
            est = self._estimate()
            if est > self.announced * (1.0 + self.grow) + self.floor:
                self.announced = est
                return True
            return False

    def _estimate(self) -> float:
        if not self._times:
            return 0.0
        return float(np.quantile(np.fromiter(self._times, float), self.quantile)) * self.margin

    def estimate(self) -> float:
        """Seconds (0 before any counted frame)."""
        with self._lock:
            return self._estimate()

    @property
    def count(self) -> int:
        return len(self._times)

    def reset(self) -> None:
        with self._lock:
            self._times.clear()
            self._seen = 0
            self.announced = 0.0


# ---- method=auto -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Rung:
    method: str
    preset: str
    prior: float  # relative cost (pull-push preview = 1), used until the rung has been measured

    @property
    def name(self) -> str:
        return f"{self.method}/{self.preset}" if self.method == "fse" else self.method


# Most accurate first (docs/BENCHMARKS.md: quality and cost of each method/preset). Priors: cost relative
# to the pull-push preview at 640x480, 30 % missing (benchmarks/pipeline.py), refined by measurement.
LADDER = (Rung("fse", "best", 40.0), Rung("fse", "balanced", 8.0), Rung("fse", "fast", 4.0),
          Rung("fse", "preview", 2.0), Rung("preview", "", 1.0))


class AutoController:
    """Picks, per frame, the most accurate rung whose predicted time fits the budget.

    Cost model: seconds = load x rel_rung x (missing + `base`): reconstruction work grows with the share
    of missing pixels (`base` covers the per-frame fixed part); rel_rung is the rung's relative cost,
    learnt when the rung runs (the prior ratio of `LADDER` scaled from the nearest measured rung before
    that), and `load` an exponential moving average (`alpha`) over every measurement, so one slow or fast
    spell of the machine moves every rung's prediction at once. Hysteresis: a frame over budget moves
    down at once (to the best rung predicted to fit, at least one step); one step up only after
    `up_after` consecutive frames under `up_margin` x budget and when the rung above is predicted under
    `up_margin` x budget too."""

    def __init__(self, ladder=LADDER, up_after: int = 15, up_margin: float = 0.7, alpha: float = 0.3,
                 base: float = 0.02, start: int | None = None):
        if not ladder:
            raise ValueError("the auto ladder is empty")
        self.ladder = tuple(ladder)
        self.up_after, self.up_margin, self.alpha, self.base = int(up_after), up_margin, alpha, base
        self.current = len(self.ladder) - 1 if start is None else int(start)
        self._rel: list[float | None] = [None] * len(self.ladder)
        self._load: float | None = None
        self._calm = 0
        self.switches = 0

    # predictions
    def cost(self, i: int) -> float | None:
        """Seconds per unit of (missing + base) of rung i at the current load; None before any frame."""
        if self._load is None:
            return None
        r = self._rel[i]
        if r is None:
            known = [(abs(j - i), j) for j, rj in enumerate(self._rel) if rj is not None]
            _, j = min(known)
            r = self._rel[j] * self.ladder[i].prior / self.ladder[j].prior
        return self._load * r

    def predict(self, i: int, missing: float) -> float | None:
        c = self.cost(i)
        return None if c is None else c * (float(missing) + self.base)

    def _best_fitting(self, budget: float, missing: float, below: int) -> int:
        """The most accurate rung at index >= below predicted to fit, else the cheapest."""
        for i in range(below, len(self.ladder)):
            p = self.predict(i, missing)
            if p is not None and p <= budget:
                return i
        return len(self.ladder) - 1

    # per frame
    def choose(self, budget: float, missing: float) -> Rung:
        """The rung to use for a frame with this missing share under this budget (seconds)."""
        cur = self.current
        p = self.predict(cur, missing)
        if p is not None and p > budget and cur < len(self.ladder) - 1:
            self._set(self._best_fitting(budget, missing, cur + 1))
        elif self._calm >= self.up_after and cur > 0:
            up = self.predict(cur - 1, missing)
            if up is not None and up <= self.up_margin * budget:
                self._set(cur - 1)
        return self.ladder[self.current]

    def record(self, rung: Rung, seconds: float, missing: float, budget: float) -> None:
        """A frame reconstructed with `rung` took `seconds` (missing share `missing`)."""
        i = self.ladder.index(rung)
        c = float(seconds) / (float(missing) + self.base)
        if self._load is None:
            self._load, self._rel[i] = c, 1.0
        elif self._rel[i] is None:
            self._rel[i] = c / self._load                       # first frame of this rung: its ratio
        else:
            self._load = (1 - self.alpha) * self._load + self.alpha * c / self._rel[i]
            self._rel[i] = 0.9 * self._rel[i] + 0.1 * c / self._load
        if i != self.current:
            return
        if seconds > budget:
            if i < len(self.ladder) - 1:
                self._set(max(i + 1, self._best_fitting(budget, missing, i + 1)))
            self._calm = 0
        elif seconds <= self.up_margin * budget:
            self._calm += 1
        else:
            self._calm = 0

    def _set(self, i: int) -> None:
        if i != self.current:
            self.current = i
            self.switches += 1
            self._calm = 0


# ---- frame sources of nrcamsrc ---------------------------------------------------------------------

class ClipCamera:
    """Frames of a clip folder written by `nrhdr simulate` (clip.json + clip.raw, memory-mapped); the files
    clip.json names must lie in the clip folder unless `allow_outside` (simulate.load_clip)."""

    def __init__(self, clip_dir, loop: bool = False, allow_outside: bool = False):
        from . import io, simulate
        self.info = simulate.load_clip(clip_dir, allow_outside=allow_outside)
        self.width, self.height = int(self.info["width"]), int(self.info["height"])
        self.fps = int(self.info["fps"])
        self.profile_path = str(self.info["profile_path"])
        self._frames = io.read_raw_video(self.info["raw_path"], self.width, self.height)
        if len(self._frames) == 0:
            raise ValueError(f"{self.info['raw_path']}: the clip has no frames")
        self.loop = loop

    def __len__(self) -> int:
        return len(self._frames)

    def frame(self, i: int) -> np.ndarray | None:
        """Frame i (uint16 H x W), wrapping round with `loop`; None past the end."""
        n = len(self._frames)
        if i >= n and not self.loop:
            return None
        return self._frames[i % n]


class SceneCamera:
    """Raw frames of an HDR scene through the simulator: the clip of `simulate.ClipRenderer` (the camera
    path of `simulate.Motion`, optional moving `objects` and a cut at `cut_frame` to `cut_scene`) over
    `frames` frames (then it repeats), noise and clipping from `sensor.capture`. Frame i is rendered when
    asked for (noise seeded by (seed, i)), so every repeat gives the same frames; rendered frames are kept
    only when the whole path fits in `cache_bytes`, so memory stays flat for any `frames`.

    `scene`: linear luminance (H, W) or planar linear RGB (3, H, W). A colour profile (`profile.cfa` a Bayer
    phase) captures the CFA mosaic of the camera RGB flux (`ClipRenderer.photosite_flux`, `sensitivity`
    R, G, B), a luminance scene being grey; a monochrome one the luminance."""

    CACHE_BYTES = 256 << 20          # rendered frames kept for the path's repeats when all of them fit
    PRERENDER_PIXELS = 10_000_000    # a path this small (all frames' pixels) may be rendered at start (< ~1 s)

    def __init__(self, scene: np.ndarray, profile, frames: int = 30, motion=None, seed: int = 0,
                 exposure_stops: float = 0.0, sensor_model=None, cache_bytes: int = CACHE_BYTES, objects=(),
                 cut_frame: int | None = None, cut_scene=None, sensitivity=(1.0, 1.0, 1.0)):
        from . import simulate
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        self.scene = np.asarray(scene, np.float32)
        if not (self.scene.ndim == 2 or simulate.is_rgb_scene(self.scene)) or min(self.scene.shape[-2:]) < 2:
            raise ValueError(f"scene must be a 2-D luminance image or planar RGB (3, H, W), got shape "
                             f"{self.scene.shape}")
        self.profile = profile
        self.width, self.height = profile.width, profile.height
        self.n = int(frames)
        self.motion = motion if motion is not None else simulate.Motion()
        self.seed, self.sensor_model = seed, sensor_model
        self._render = simulate.ClipRenderer(self.scene, profile, self.n, exposure_stops, self.motion, objects,
                                             cut_frame, cut_scene, sensitivity=sensitivity)
        self.k = self._render.scale
        self._keep = self.n * self.width * self.height * 2 <= cache_bytes
        self._frames: dict = {}

    def __len__(self) -> int:
        return self.n

    def prerender(self, max_pixels: int = PRERENDER_PIXELS) -> bool:
        """Render the whole path now when it is small (a live source then keeps its frame rate from the
        first frame); True when done."""
        if not self._keep or self.n * self.width * self.height > max_pixels:
            return False
        for i in range(self.n):
            self.frame(i)
        return True

    def frame(self, k: int) -> np.ndarray:
        """Raw frame k (uint16 H x W) of the repeating path."""
        from . import sensor
        i = k % self.n
        f = self._frames.get(i)
        if f is None:
            r = self._render
            f = sensor.capture(r.photosite_flux(r.flux(i)), self.profile, np.random.default_rng((self.seed, i)),
                               sensor_model=self.sensor_model)
            if self._keep:
                self._frames[i] = f
        return f


def load_scene(arg: str, height: int = 1200, cfa: str = "none") -> tuple[np.ndarray, str]:
    """The scene of a camera with CFA `cfa` (cfa.CFAS; a profile's `cfa`): an HDR file's linear luminance
    (monochrome) or planar linear RGB (3, H, W) (`io.read_rgb`, a Bayer phase); for 'synthetic' the
    synthesised scene (4:3; in colour `simulate.tint_synthetic`) at twice `height` rows, at most the 1200 rows
    `nrhdr simulate` uses (small frames need no big scene), through the scene file cache
    (`scene.cached_synthetic_hdr_scene`)."""
    from pathlib import Path

    from . import cfa as cfas
    from . import io, scene, simulate
    colour = cfas.is_colour(cfas.check(cfa, "cfa"))
    if arg in ("", "synthetic"):
        h = int(min(1200, max(120, 2 * height)))
        lum = scene.cached_synthetic_hdr_scene(h, h * 4 // 3)
        return (simulate.tint_synthetic(lum) if colour else lum), "synthetic"
    return (io.read_rgb(arg) if colour else io.read_luminance(arg)), Path(arg).name


# ---- numba compilations ----------------------------------------------------------------------------

class JitWatch:
    """Counts numba compilations (cache misses: numba only compiles when its on-disk cache has no entry)
    in this process via numba's event API. `snapshot()` -> (count, seconds); installed once, lazily."""

    _installed = False
    _lock = threading.Lock()
    count = 0
    seconds = 0.0
    names: collections.deque = collections.deque(maxlen=64)

    @classmethod
    def install(cls) -> None:
        with cls._lock:
            if cls._installed:
                return
            from numba.core import event as ev

            class _Listener(ev.Listener):
                _local = threading.local()

                def on_start(self, event):
                    d = getattr(self._local, "depth", 0)
                    self._local.depth = d + 1
                    if d == 0:
                        self._local.t0 = time.perf_counter()

                def on_end(self, event):
                    d = getattr(self._local, "depth", 1) - 1
                    self._local.depth = d
                    fn = getattr((event.data or {}).get("dispatcher"), "py_func", None)
                    with JitWatch._lock:
                        JitWatch.count += 1
                        JitWatch.names.append(f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', '?')}")
                        if d == 0:
                            JitWatch.seconds += time.perf_counter() - getattr(self._local, "t0",
                                                                              time.perf_counter())

            ev.register("numba:compile", _Listener())
            cls._installed = True

    @classmethod
    def snapshot(cls) -> tuple[int, float]:
        cls.install()
        with cls._lock:
            return cls.count, cls.seconds

    @classmethod
    def since(cls, snap: tuple[int, float]) -> tuple[int, float, list[str]]:
        """Compilations since `snap`: (count, seconds, up to 8 of the nrhdr_core kernels they compiled)."""
        cls.install()
        with cls._lock:
            n = cls.count - snap[0]
            names = sorted({m for m in list(cls.names)[-n:] if m.startswith("nrhdr_core")})[:8] if n > 0 else []
            return n, cls.seconds - snap[1], names
