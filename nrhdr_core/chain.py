"""The per-frame chain of the GStreamer elements as one function (paper 2.3 Eq. 3, 3.2, 2.2/2.4, 5):
raw frame -> validity -> crosstalk -> reconstruction (-> log tone mapping), for batch reprocessing.

`process_frame` makes exactly the core calls the elements make, with the same parameters, so its output
equals `nrvalidity ! nrcrosstalk ! nrreconstruct ! nrexrsink write-state=true` bit for bit
(tests/test_batch.py checks it against the real pipeline):

- nrvalidity:    ``validity.classify(raw, profile, mode=mode, l_min=l_min, dark_policy=dark_policy)`` (l_min None =
  the profile's)
- nrcrosstalk:   ``crosstalk.correct(values, state, crosstalk_profile, mode, lut=crosstalk_lut)`` unless mode is
  'off'
- nrreconstruct: ``reconstruction.reconstruct_frame(values, state, method=, preset=, use_bounds=,
  noise=profile, fusion=noise_fusion)`` (known mask and bounds in one pass, reconstruction, NOISY pixels fused with the
  profile's noise model, missing pixels written back with the RECONSTRUCTED bit); a colour profile (`profile.cfa`
  a Bayer phase): ``demosaic.reconstruct_cfa(values, state, profile.cfa, method=, preset=, use_bounds=,
  noise=profile, fusion=noise_fusion)``, the (3, H, W) RGB frame (methods of `COLOUR_METHODS`); with ``temporal=on``
  ``temporal.TemporalReconstructor(method=, preset=, use_bounds=, fusion=).process(values, state, profile)``,
  one instance per stream, passed to `process_frame` (it holds the past frames)
- nrexrsink:     ``io.write_exr(path, values, state)``
- nrtonemap (normalise=caps/fixed): ``tonemap.log_tonemap(values, white, exposure_stops=, contrast=)``
  with white = the profile's white (the caps' field) unless given.

The settings' vocabularies are the stages' own (`validity.MODES`, `validity.DARK_POLICIES`, `crosstalk.MODES`,
`crosstalk.LUT_FORMS`, `reconstruction.METHODS`, `reconstruction.FUSIONS`, `fse.FSE_PRESETS`,
`tonemap.TRANSFERS`, TEMPORAL_MODES). `warmup` is the one entry point that compiles the chain's numba kernels
(`nrhdr warmup`, the elements' start, `nrhdr batch`).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import numpy as np

from .crosstalk import LUT_FORMS
from .crosstalk import MODES as CROSSTALK_MODES
from .fse import FSE_PRESETS
from .reconstruction import FUSIONS as NOISE_FUSIONS
from .reconstruction import METHODS
from .tonemap import SDR_OPERATORS
from .tonemap import TRANSFERS as HDR_TRANSFERS
from .validity import DARK_POLICIES
from .validity import MODES as VALIDITY_MODES

PRESETS = tuple(FSE_PRESETS)
TRANSFERS = ("log",) + HDR_TRANSFERS     # nrtonemap's: the log tone map, or a BT.2100 HDR encoding
STAGES = ("validity", "crosstalk", "reconstruction", "tonemap")
TEMPORAL_MODES = ("off", "on")           # nrreconstruct temporal
TEMPORAL_BUDGET = 75                     # nrreconstruct temporal-budget: blocks' worth of FSE work a frame
                                         # (docs/TEMPORAL.md)
MAX_TEMPORAL_BUDGET = 1 << 20
COLOUR_METHODS = ("preview", "fse")      # the reconstruction methods of a colour mosaic (demosaic.METHODS)


@dataclasses.dataclass(frozen=True)
class ChainSettings:
    """The elements' properties that change the output. Defaults are pipelines/raw_to_exr.sh's."""
    mode: str = "threshold"          # nrvalidity mode
    l_min: float | None = None       # nrvalidity l-min (None = the profile's; the element's -1)
    dark_policy: str = "weighted"    # nrvalidity dark-policy
    crosstalk: str = "kernel"        # nrcrosstalk mode
    crosstalk_lut: str = "compact"   # nrcrosstalk lut (mode=lut: compact = fast, full = accurate)
    method: str = "fse"              # nrreconstruct method
    preset: str = "fast"             # nrreconstruct preset
    use_bounds: bool = True          # nrreconstruct use-bounds
    noise_fusion: str = "auto"       # nrreconstruct noise-fusion (NOISY pixels: auto, accurate or fast)
    temporal: str = "off"            # nrreconstruct temporal (on: `process_frame` needs a TemporalReconstructor)
    temporal_budget: int = TEMPORAL_BUDGET   # nrreconstruct temporal-budget (blocks' worth a frame; 0 = no bound)
    operator: str = "local"          # nrtonemap operator (tonemap.SDR_OPERATORS; docs/TONEMAP.md)
    white: float | None = None       # nrtonemap white (None = the profile's white, as in the caps)
    exposure: float = 0.0            # nrtonemap exposure (stops)
    contrast: float = 1000.0         # nrtonemap contrast (= tonemap.DEFAULT_CONTRAST)

    def __post_init__(self):
        for name, allowed in (("mode", VALIDITY_MODES), ("dark_policy", DARK_POLICIES),
                              ("crosstalk", CROSSTALK_MODES), ("crosstalk_lut", LUT_FORMS), ("method", METHODS),
                              ("preset", PRESETS), ("noise_fusion", NOISE_FUSIONS), ("temporal", TEMPORAL_MODES),
                              ("operator", SDR_OPERATORS)):
            v = getattr(self, name)
            if v not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}, got {v!r}")
        b = self.temporal_budget
        if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or not 0 <= b <= MAX_TEMPORAL_BUDGET:
            raise ValueError(f"temporal_budget must be an integer in 0..{MAX_TEMPORAL_BUDGET}, got {b!r}")
        if self.l_min is not None and not (0.0 <= float(self.l_min) <= 65535.0):
            raise ValueError(f"l_min must be in 0..65535 (or None for the profile's), got {self.l_min}")
        if self.white is not None and not (float(self.white) > 0 and np.isfinite(self.white)):
            raise ValueError(f"white must be a finite number > 0 (or None for the profile's), got {self.white}")
        if not (float(self.contrast) > 0 and np.isfinite(self.contrast)):
            raise ValueError(f"contrast must be > 0, got {self.contrast}")

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def process_frame(raw: np.ndarray, profile, settings: ChainSettings = ChainSettings(), crosstalk_profile=None,
                  temporal=None):
    """One raw frame (uint16 (H, W)) through validity, crosstalk and reconstruction, as the elements do it.
    `crosstalk_profile`: the profile whose calibration nrcrosstalk applies (its `profile` property);
    None = `profile` (nrcrosstalk reads the one nrvalidity names in the caps). `temporal`: a
    `temporal.TemporalReconstructor` (`temporal_for(settings)`) that reconstructs instead of
    `reconstruct_frame`, with the frames it was given before as its past (required with
    settings.temporal "on"; frames in stream order). Returns (values float32, state uint8), what
    nrexrsink writes: values (H, W), or for a colour profile the RGB frame (3, H, W) of
    `demosaic.reconstruct_cfa` (method preview or fse, temporal off) with the mosaic's state."""
    from . import cfa, crosstalk, reconstruction, validity
    s = settings
    colour = cfa.is_colour(profile.cfa)
    if colour:
        check_colour(s, profile.cfa)
    if s.temporal == "on" and temporal is None:
        raise ValueError("process_frame: settings.temporal 'on' needs the stream's TemporalReconstructor "
                         "(temporal=chain.temporal_for(settings))")
    values, state = validity.classify(raw, profile, mode=s.mode, l_min=s.l_min, dark_policy=s.dark_policy)
    if s.crosstalk != "off":
        xt = profile if crosstalk_profile is None else crosstalk_profile
        if (xt.width, xt.height) != (profile.width, profile.height):
            raise ValueError(f"crosstalk profile {xt.path} has a {xt.width}x{xt.height} mask but the frames "
                             f"are {profile.width}x{profile.height}")
        v2, s2 = crosstalk.correct(values, state, xt, s.crosstalk, lut=s.crosstalk_lut)
        if v2 is not values:
            values[...] = v2
        if s2 is not state:
            state[...] = s2
    # nrreconstruct's own frame path (one function, so batch and the element give the same bits)
    if colour:
        from . import demosaic
        rgb = demosaic.reconstruct_cfa(values, state, profile.cfa, method=s.method, preset=s.preset,
                                       use_bounds=s.use_bounds, noise=profile, fusion=s.noise_fusion)
        return rgb, state
    if temporal is not None:
        temporal.process(values, state, noise=profile)
    else:
        reconstruction.reconstruct_frame(values, state, method=s.method, preset=s.preset,
                                         use_bounds=s.use_bounds, noise=profile, fusion=s.noise_fusion)
    return values, state


def check_colour(settings: ChainSettings, cfa: str) -> None:
    """ValueError naming the setting when `settings` cannot reconstruct a colour mosaic of `cfa`
    (nrreconstruct refuses the same: method linear/nearest, temporal on)."""
    if settings.method not in COLOUR_METHODS:
        raise ValueError(f"method {settings.method!r} works on monochrome frames only; a colour mosaic (cfa "
                         f"{cfa}) takes method {' or '.join(COLOUR_METHODS)}")
    if settings.temporal == "on":
        raise ValueError(f"temporal 'on' works on monochrome frames only; a colour mosaic (cfa {cfa}) takes "
                         f"temporal 'off'")


def temporal_for(settings: ChainSettings):
    """The `temporal.TemporalReconstructor` nrreconstruct temporal=on runs with `settings` (one per stream)."""
    from .temporal import TemporalReconstructor
    s = settings
    return TemporalReconstructor(method=s.method, preset=s.preset, use_bounds=s.use_bounds, fusion=s.noise_fusion,
                                 budget=int(s.temporal_budget))


def tonemap_frame(values: np.ndarray, profile, settings: ChainSettings = ChainSettings(),
                  local=None) -> np.ndarray:
    """nrtonemap (normalise=caps, or fixed with `white`; `settings.operator`) to GRAY8: uint8 (H, W).
    operator "local": `local` is the stream's `tonemap.LocalTonemap` (its statistics smoothed over the frames
    it saw, as in the element); None = one for this frame alone (the element's first frame)."""
    from . import tonemap
    white = float(settings.white) if settings.white is not None else float(profile.white)
    if settings.operator == "local":
        local = tonemap.LocalTonemap() if local is None else local
        return local(values, white, exposure_stops=settings.exposure, contrast=settings.contrast)
    return tonemap.log_tonemap(values, white, exposure_stops=settings.exposure, contrast=settings.contrast)


def _warm_frame(prof, s: ChainSettings, raw: np.ndarray):
    """(values, state) of the kind `validity.classify` makes with settings `s` (every state the settings can
    produce, in both pixel kinds), written in numpy so that a stage's warm-up compiles only its own kernels."""
    from .states import ATTENUATED, CLIPPED, DARK, DISCARDED, NOISY
    att = prof.mask
    values = (np.maximum(raw.astype(np.float32) - np.float32(prof.black_level), np.float32(1.0))
              * np.where(att, np.float32(prof.nd), np.float32(1.0))).astype(np.float32)
    reason = np.zeros(raw.shape, np.uint8)
    reason[:, -3:] = CLIPPED
    reason[:, :2] = DARK
    if s.mode == "threshold" and s.dark_policy == "weighted":
        reason[::2, 2] = NOISY
    if s.mode == "best":
        reason[1::3, 4:8] = DISCARDED
    state = (reason | np.where(att, np.uint8(ATTENUATED), np.uint8(0))).astype(np.uint8)
    return values, state


def _warm_method(method: str) -> None:
    """Reconstruction `method` through the public calls on small frames that reach the kernels the
    chain's own 12 x 16 frame does not: the nearest fill's distance transform (a target more than
    `fill.RING_RADIUS_MAX` from any source), the preview's parallel pyramid levels (from 512 x 512 on),
    FSE's presets, log domain, skipped pixels and fallback (an area no block can fill), the data-range
    clamp, the noise fusions, both bound settings."""
    from types import SimpleNamespace

    from . import fill, fse, reconstruction
    from .states import ATTENUATED, CLIPPED, DARK, NOISY, VALID
    rec = reconstruction.reconstruct
    noise = SimpleNamespace(gain=0.55, read_noise=2.0, nd=6.35)
    v = np.zeros((4, 4), np.float32)
    k = np.ones((4, 4), bool)
    k[1, 1] = False
    nan = np.full(v.shape, np.nan, np.float32)
    kf = np.zeros((2, 80), bool)
    kf[:, 0] = True
    fill.nearest(np.ones((2, 80), np.float32), kf)
    rec(v, k, method="nearest" if method == "fse" else method, lower=nan)
    reconstruction.fuse_noisy(v.copy(), v, k, ~k, noise)
    if method == "preview":
        kp = np.ones((512, 512), bool)
        kp[1, 1] = False
        rec(np.ones((512, 512), np.float32), kp, method="preview")
    if method == "fse":
        rng = np.random.default_rng(0)
        v24 = rng.random((24, 24)).astype(np.float32)
        k24 = rng.random((24, 24)) < 0.5
        n24 = np.full_like(v24, np.nan)
        for preset in ("preview", "balanced"):
            fse.fse_reconstruct(v24, k24, lower=n24, upper=n24, preset=preset)
        # HDR data (12 stops, a clipped and a dark bound): the log domain's passes
        hv = (2.0 ** (12.0 * v24)).astype(np.float32)
        lo, hi = n24.copy(), n24.copy()
        lo[0, 0] = hv.max()
        hi[1, 1] = hv.min()
        fse.fse_reconstruct(hv, k24, lower=lo, upper=hi, preset="preview")
        # NOISY pixels skipped by FSE and given their noise level (the accurate fusion)
        rec(v24, k24, method="fse", preset="preview", noisy=~k24 & (rng.random((24, 24)) < 0.5), noise=noise,
            fusion="accurate", noisy_skip=True)
        # an area whose support windows hold skipped pixels only: the fallback
        v64 = (2.0 ** (rng.random((64, 64)) * 8)).astype(np.float32)
        k64 = np.zeros((64, 64), bool)
        k64[:, :8] = rng.random((64, 8)) < 0.6
        skip = ~k64
        skip[20:44, 36:60] = False
        fse.fse_reconstruct(v64, k64, preset="fast", skip=skip)
    # tiny frames: clipped and dark bounds on and off, NOISY pixels fused (nrvalidity dark-policy=weighted)
    state = np.zeros((4, 4), np.uint8)
    state[1, 1] = CLIPPED
    state[2, 2] = DARK
    reconstruction.reconstruct_frame(v.copy(), state, method=method, preset="preview", use_bounds=True)
    reconstruction.reconstruct_frame(v.copy(), state.copy(), method=method, preset="preview", use_bounds=False)
    state = np.full((4, 4), ATTENUATED | CLIPPED, np.uint8)
    state[0, :] = VALID
    state[1, 1] = CLIPPED
    state[2, 2] = ATTENUATED | NOISY
    reconstruction.reconstruct_frame(v.copy() + 1, state, method=method, preset="preview", use_bounds=True,
                                     noise=noise)


def _warm_temporal(prof, s: ChainSettings, raw: np.ndarray) -> None:
    """`temporal_for(s)` over a frame alone, steady ones until their blocks are settled (block judgement,
    averaging, the reconstruction of what is left, the fusion with the past, the finished still blocks), a cut
    after them (the finished blocks' input restored), one moved by a pixel (the aligned past) and one moved by
    three (the phase correlation of `temporal.global_motion`); the frame and mask tiled 2 x 2, so that the
    correlation has its 4 x 4 cells; and under a budget of one block, so that the budgeted path (the preview
    start, the blocks chosen by their work) is compiled whatever the frame's size."""
    prof = prof.replace(mask=np.tile(prof.mask, (2, 2)), defects=None)
    raw = np.tile(raw, (2, 2))
    cut = np.ascontiguousarray(raw[::-1, ::-1])
    for tr in (temporal_for(s), temporal_for(dataclasses.replace(s, temporal_budget=1))):
        for frame in [raw] * 6 + [cut, np.roll(cut, 1, axis=1), np.roll(cut, 4, axis=1)]:
            values, state = _warm_frame(prof, s, frame)
            tr.process(values, state, noise=prof)


def _padded(a: np.ndarray, pad: int) -> np.ndarray:
    """`a` as a view with rows `pad` elements longer than its width (GStreamer pads video rows to 4 bytes)."""
    out = np.zeros((a.shape[0], a.shape[1] + pad), a.dtype)[:, :a.shape[1]]
    out[...] = a
    return out


def _read_only(a: np.ndarray) -> np.ndarray:
    a = a.copy() if a.flags.c_contiguous else a
    a.setflags(write=False)
    return a


def _warm_colour(prof, sets, raw: np.ndarray, elements: bool) -> None:
    """`demosaic.reconstruct_cfa` with each setting of a colour method (its kernels and signatures; a
    read-only mosaic as nrreconstruct maps its input with `elements`)."""
    from . import demosaic
    demosaic.warmup()
    for s in {(s.method, s.preset, s.use_bounds, s.noise_fusion, s.mode, s.dark_policy): s
              for s in sets if s.method in COLOUR_METHODS}.values():
        values, state = _warm_frame(prof, s, raw)
        for v in [values] + ([_read_only(values)] if elements else []):
            demosaic.reconstruct_cfa(v, state.copy(), prof.cfa, method=s.method, preset=s.preset,
                                     use_bounds=s.use_bounds, noise=prof, fusion=s.noise_fusion,
                                     out=np.empty((3,) + raw.shape, np.float32))


def warmup(settings: ChainSettings | Iterable[ChainSettings] = ChainSettings(), tone: bool = False,
           calibrated: bool = True, *, stages: Iterable[str] = STAGES, transfers: Iterable[str] = (),
           elements: bool = False, cfa: str = "none") -> None:
    """Compile (or load from numba's cache) exactly the kernels and signatures the chain runs with `settings`
    (one `ChainSettings` or several), on a tiny synthetic frame. Never called at import; `nrhdr warmup`, the
    elements' start and `batch` call it.

    - `stages` (of STAGES): ``validity`` (`validity.classify`), ``crosstalk`` (`crosstalk.correct`; nothing
      with mode off or without a calibration), ``reconstruction`` (each method on the frames of `_warm_method`,
      then `reconstruction.reconstruct_frame` with the settings' preset, bounds and noise fusion),
      ``tonemap`` (the `transfers`). Each stage's input frame is made in numpy, so a stage compiles its own
      kernels only.
    - `tone`: the tone map of `tonemap_frame` (the same as "log" in `transfers`; the local operator too when a
      setting's `operator` is "local").
    - `transfers` (of TRANSFERS): nrtonemap's outputs: "log" (GRAY8, and GRAY16 with `elements`), "pq",
      "hlg" (`tonemap.hdr_encode`).
    - `calibrated`: the profile has a crosstalk calibration (an identity one here), as nrcrosstalk applies it;
      with a Bayer `cfa` also one with per-colour amplitudes.
    - `elements`: also the array types of the GStreamer elements' mapped buffers, which numba compiles
      apart: read-only raw frames with packed or padded rows (nrvalidity), a read-only HDR frame and padded
      output rows (nrtonemap).
    - `cfa`: the profile's CFA; a Bayer phase warms the stages on a mosaic of it, and the reconstruction
      stage compiles `demosaic.reconstruct_cfa` (methods of COLOUR_METHODS) instead of the monochrome path."""
    from . import cfa as cfas
    from . import crosstalk, profile, reconstruction, tonemap, validity
    colour = cfas.is_colour(cfas.check(cfa, "warm-up cfa"))
    sets = [settings] if isinstance(settings, ChainSettings) else list(settings)
    stages = tuple(stages)
    transfers = tuple(transfers) + (("log",) if tone else ())
    for name, given, allowed in (("stage", stages, STAGES), ("transfer", transfers, TRANSFERS)):
        bad = [x for x in given if x not in allowed]
        if bad:
            raise ValueError(f"warm-up {name} must be one of {', '.join(allowed)}, got {bad[0]!r}")
    h, w = 12, 16
    mask = np.random.default_rng(0).random((h, w)) < 0.5
    prof = profile.make(mask, cfa=cfa) if colour else profile.make(mask)
    _, xx = np.mgrid[0:h, 0:w]
    raw = np.clip(10.0 ** (0.5 + 3.8 * xx / (w - 1)), 0, prof.max_code).astype(np.uint16)

    if "validity" in stages:
        raws = [raw] + ([_read_only(raw), _read_only(_padded(raw, 2))] if elements else [])
        for mode, dark_policy, l_min in dict.fromkeys((s.mode, s.dark_policy, s.l_min) for s in sets):
            for r in raws:
                validity.classify(r, prof, mode=mode, l_min=l_min, dark_policy=dark_policy)

    if "crosstalk" in stages and calibrated:
        # a colour camera's calibration with and without per-colour amplitudes (`calibration.colour_spill`)
        calibs = [crosstalk.identity_calibration(mask, nd=prof.nd, black_level=prof.black_level,
                                                 clip_code=prof.clip_code, colour=c)
                  for c in ((False, True) if colour else (False,))]
        for s in {(s.crosstalk, s.crosstalk_lut): s for s in sets if s.crosstalk != "off"}.values():
            for c in calibs:
                values, state = _warm_frame(prof, s, raw)
                crosstalk.correct(values, state, prof.replace(crosstalk=c), s.crosstalk, lut=s.crosstalk_lut)

    if "reconstruction" in stages and colour:
        _warm_colour(prof, sets, raw, elements)
    elif "reconstruction" in stages:
        for method in dict.fromkeys(s.method for s in sets):
            _warm_method(method)
        for s in {(s.method, s.preset, s.use_bounds, s.noise_fusion, s.mode, s.dark_policy): s
                  for s in sets}.values():
            values, state = _warm_frame(prof, s, raw)
            reconstruction.reconstruct_frame(values, state, method=s.method, preset=s.preset,
                                             use_bounds=s.use_bounds, noise=prof, fusion=s.noise_fusion)
            if s.temporal == "on":
                _warm_temporal(prof, s, raw)

    if "tonemap" in stages and transfers:
        values, _ = _warm_frame(prof, sets[0], raw)
        inputs = [values] + ([_read_only(values)] if elements else [])
        white = float(prof.white)
        for transfer in dict.fromkeys(transfers):
            dtypes = (np.uint8, np.uint16) if transfer == "log" and elements else (
                (np.uint8,) if transfer == "log" else (np.uint16,))
            for v in inputs:
                for dt in dtypes:
                    for out in [np.empty((h, w), dt)] + ([_padded(np.empty((h, w), dt), 4)] if elements else []):
                        if transfer == "log":
                            tonemap.log_tonemap(v, white, out=out)
                        else:
                            tonemap.hdr_encode(v, white, transfer, out=out)
        if "log" in transfers and any(s.operator == "local" for s in sets):
            tonemap.warmup_local(elements=elements)
