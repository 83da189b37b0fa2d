"""The per-frame chain of the GStreamer elements as one function (paper 2.3 Eq. 3, 3.2, 2.2/2.4, 5):
raw frame -> validity -> crosstalk -> reconstruction (-> log tone mapping), for batch reprocessing.

`process_frame` makes exactly the core calls the elements make, with the same parameters, so its output
equals `nrvalidity ! nrcrosstalk ! nrreconstruct ! nrexrsink write-state=true` bit for bit
(tests/test_batch.py checks it against the real pipeline):

- nrvalidity:    ``validity.classify(raw, profile, mode=mode, l_min=l_min, dark_policy=dark_policy)`` (l_min None =
  the profile's)
- nrcrosstalk:   ``crosstalk.correct(values, state, crosstalk_profile, mode)`` unless mode is 'off'
- nrreconstruct: ``reconstruction.reconstruct_frame(values, state, method=, preset=, use_bounds=,
  noise=profile, fusion=noise_fusion)`` (known mask and bounds in one pass, reconstruction, NOISY pixels fused with the
  profile's noise model, missing pixels written back with the RECONSTRUCTED bit)
- nrexrsink:     ``io.write_exr(path, values, state)``
- nrtonemap (normalise=caps/fixed): ``tonemap.log_tonemap(values, white, exposure_stops=, contrast=)``
  with white = the profile's white (the caps' field) unless given.
"""
from __future__ import annotations

import dataclasses

import numpy as np

CROSSTALK_MODES = ("kernel", "lut", "off")      # nrcrosstalk's modes (default kernel)
VALIDITY_MODES = ("all", "best", "threshold")   # nrvalidity's modes (default threshold)
DARK_POLICIES = ("weighted", "threshold")       # nrvalidity's dark-policy (default weighted, issue 8)
METHODS = ("fse", "linear", "nearest", "preview")
PRESETS = ("preview", "fast", "balanced", "best")


@dataclasses.dataclass(frozen=True)
class ChainSettings:
    """The elements' properties that change the output. Defaults are pipelines/raw_to_exr.sh's."""
    mode: str = "threshold"          # nrvalidity mode
    l_min: float | None = None       # nrvalidity l-min (None = the profile's; the element's -1)
    dark_policy: str = "weighted"    # nrvalidity dark-policy
    crosstalk: str = "kernel"        # nrcrosstalk mode
    crosstalk_lut: str = "compact"   # nrcrosstalk lut (mode=lut: compact = fast, full = accurate; issue 7)
    method: str = "fse"              # nrreconstruct method
    preset: str = "fast"             # nrreconstruct preset
    use_bounds: bool = True          # nrreconstruct use-bounds
    noise_fusion: str = "auto"       # nrreconstruct noise-fusion (NOISY pixels: auto, accurate or fast)
    white: float | None = None       # nrtonemap white (None = the profile's white, as in the caps)
    exposure: float = 0.0            # nrtonemap exposure (stops)
    contrast: float = 1000.0         # nrtonemap contrast (= tonemap.DEFAULT_CONTRAST)

    def __post_init__(self):
        for name, allowed in (("mode", VALIDITY_MODES), ("dark_policy", DARK_POLICIES), ("crosstalk", CROSSTALK_MODES),
                              ("crosstalk_lut", ("compact", "full")), ("method", METHODS), ("preset", PRESETS),
                              ("noise_fusion", ("auto", "accurate", "fast"))):
            v = getattr(self, name)
            if v not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}, got {v!r}")
        if self.l_min is not None and not (0.0 <= float(self.l_min) <= 65535.0):
            raise ValueError(f"l_min must be in 0..65535 (or None for the profile's), got {self.l_min}")
        if self.white is not None and not (float(self.white) > 0 and np.isfinite(self.white)):
            raise ValueError(f"white must be a finite number > 0 (or None for the profile's), got {self.white}")
        if not (float(self.contrast) > 0 and np.isfinite(self.contrast)):
            raise ValueError(f"contrast must be > 0, got {self.contrast}")

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def process_frame(raw: np.ndarray, profile, settings: ChainSettings = ChainSettings(), crosstalk_profile=None):
    """One raw frame (uint16 (H, W)) through validity, crosstalk and reconstruction, as the elements do it.
    `crosstalk_profile`: the profile whose calibration nrcrosstalk applies (its `profile` property);
    None = `profile` (nrcrosstalk reads the one nrvalidity names in the caps). Returns (values float32,
    state uint8), what nrexrsink writes."""
    from . import crosstalk, reconstruction, validity
    s = settings
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
    reconstruction.reconstruct_frame(values, state, method=s.method, preset=s.preset,
                                     use_bounds=s.use_bounds, noise=profile, fusion=s.noise_fusion)
    return values, state


def tonemap_frame(values: np.ndarray, profile, settings: ChainSettings = ChainSettings()) -> np.ndarray:
    """nrtonemap (normalise=caps, or fixed with `white`) to GRAY8: uint8 (H, W)."""
    from . import tonemap
    white = float(settings.white) if settings.white is not None else float(profile.white)
    return tonemap.log_tonemap(values, white, exposure_stops=settings.exposure, contrast=settings.contrast)


def warmup(settings: ChainSettings = ChainSettings(), tone: bool = False, calibrated: bool = True) -> None:
    """Compile (or load from numba's cache) exactly the kernels and signatures `process_frame` uses with
    `settings`, by running it on a tiny synthetic frame with dark, valid and clipped pixels of both kinds
    (`calibrated`: with an identity crosstalk calibration, as a calibrated profile would). Never called at
    import."""
    from . import crosstalk
    from . import profile as profile_mod
    rng = np.random.default_rng(0)
    mask = rng.random((12, 16)) < 0.5
    prof = profile_mod.make(mask)
    if calibrated and settings.crosstalk != "off":
        prof = prof.replace(crosstalk=crosstalk.identity_calibration(mask, nd=prof.nd,
                                                                     black_level=prof.black_level,
                                                                     clip_code=prof.clip_code))
    _, xx = np.mgrid[0:12, 0:16]
    raw = np.clip(10.0 ** (0.5 + 3.8 * xx / 15.0), 0, prof.max_code).astype(np.uint16)
    values, _ = process_frame(raw, prof, settings)
    if calibrated and settings.crosstalk != "off":
        process_frame(raw, prof.replace(crosstalk=None), settings)
    if tone:
        tonemap_frame(values, prof, settings)
