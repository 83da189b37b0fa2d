"""Camera profile: one versioned JSON file describing a non-regular ND sensor (docs/PROFILE.md).

The JSON names the ND mask (an 8-bit PNG beside it, 255 = attenuated) and, once calibrated, the crosstalk
calibration (an .npz beside it, see `crosstalk.py` / `calibration.py`). `load` validates everything and
raises `ProfileError` naming the file and the field at fault.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from . import io

FORMAT = "nrhdr-camera-profile"
VERSION = 1


class ProfileError(ValueError):
    """A camera profile is missing, unreadable or inconsistent; the message names file and field."""


@dataclasses.dataclass(frozen=True, eq=False)
class CameraProfile:
    """A sensor with a non-regular ND mask (paper section 2.3). Codes are `bit_depth`-bit ADC values."""
    mask: np.ndarray                  # bool (H, W), True = attenuated
    nd: float = 6.35                  # ND factor, Eq. 1 (paper's prototype: ~6.35)
    bit_depth: int = 12
    clip_code: int = 4094             # codes >= clip_code are clipped (paper: DN_max = 4095 - 1)
    black_level: float = 0.0          # code of zero light
    gain: float = 4400.0 / 8000.0     # DN per electron: the ADC clips before the full well, so saturated
                                      # pixels always read >= clip_code despite read noise
    read_noise: float = 2.0           # electrons rms
    full_well: float = 8000.0         # electrons
    l_min: float = 100.0              # attenuated pixels below this signal (code - black) are invalid (2.3)
    name: str = "camera"
    crosstalk: Any = None             # crosstalk.CrosstalkCalibration or None (identity)
    crosstalk_file: str | None = None
    extra: dict = dataclasses.field(default_factory=dict)
    path: Path | None = None

    @property
    def height(self) -> int:
        return int(self.mask.shape[0])

    @property
    def width(self) -> int:
        return int(self.mask.shape[1])

    @property
    def max_code(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def white(self) -> float:
        """Largest scaled linear value the sensor represents: (clip_code - black) * ND (paper 4.1)."""
        return (self.clip_code - self.black_level) * self.nd

    @property
    def regular_white(self) -> float:
        return float(self.clip_code - self.black_level)

    def replace(self, **changes) -> "CameraProfile":
        p = dataclasses.replace(self, **changes)
        validate(p)
        return p


def validate(p: CameraProfile, where: str = "profile") -> None:
    """Check physical consistency; raise ProfileError naming the field."""
    def bad(field, msg):
        raise ProfileError(f"{where}: field '{field}': {msg}")
    m = p.mask
    if not isinstance(m, np.ndarray) or m.ndim != 2 or m.dtype != bool or m.size == 0:
        bad("mask", "must be a non-empty 2-D boolean array")
    for f in ("nd", "gain", "full_well"):
        v = getattr(p, f)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            bad(f, f"must be a finite number > 0, got {v!r}")
    if p.nd < 1:
        bad("nd", f"must be >= 1 (attenuation), got {p.nd}")
    if not (isinstance(p.bit_depth, int) and 1 <= p.bit_depth <= 16):
        bad("bit_depth", f"must be an integer 1..16, got {p.bit_depth!r}")
    if not (0 < p.clip_code <= p.max_code):
        bad("clip_code", f"must be in 1..{p.max_code} for {p.bit_depth}-bit data, got {p.clip_code}")
    if not (0 <= p.black_level < p.clip_code):
        bad("black_level", f"must be in 0..clip_code-1, got {p.black_level}")
    if not (math.isfinite(p.read_noise) and p.read_noise >= 0):
        bad("read_noise", f"must be >= 0, got {p.read_noise}")
    sat = p.full_well * p.gain + p.black_level
    if sat < p.clip_code + 3.0 * p.read_noise * p.gain:
        bad("gain", f"full_well * gain + black_level = {sat:.1f} DN does not reach clip_code "
                    f"{p.clip_code} by 3 sigma of read noise: saturated pixels would read as valid")
    if not (math.isfinite(p.l_min) and 0 <= p.l_min < p.clip_code - p.black_level):
        bad("l_min", f"must be in 0..clip_code-black_level, got {p.l_min}")


def make(mask: np.ndarray, **fields) -> CameraProfile:
    p = CameraProfile(mask=np.asarray(mask, dtype=bool), **fields)
    validate(p)
    return p


_SCALARS = {"nd": float, "bit_depth": int, "clip_code": int, "black_level": float, "gain": float,
            "read_noise": float, "full_well": float, "l_min": float, "name": str}


def save(p: CameraProfile, path) -> Path:
    """Write `path` (JSON), the mask PNG and the crosstalk calibration beside it, atomically."""
    validate(p)
    path = Path(path)
    stem = path.stem
    mask_name = f"{stem}_mask.png"
    io.write_mask(path.parent / mask_name, p.mask)
    doc: dict[str, Any] = {"format": FORMAT, "version": VERSION, "width": p.width, "height": p.height,
                           "mask": mask_name}
    for k in _SCALARS:
        doc[k] = getattr(p, k)
    doc["crosstalk"] = None
    if p.crosstalk is not None:
        from . import crosstalk
        xt_name = f"{stem}_crosstalk.npz"
        doc["crosstalk"] = crosstalk.save_calibration(p.crosstalk, path.parent / xt_name)
    if p.extra:
        doc["extra"] = p.extra
    _write_json_atomic(path, doc)
    return path


def _write_json_atomic(path: Path, doc: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name("." + path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    os.replace(tmp, path)


def load(path) -> CameraProfile:
    """Read and validate a camera profile JSON (docs/PROFILE.md)."""
    path = Path(path)
    if not path.is_file():
        raise ProfileError(f"{path}: camera profile not found")
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ProfileError(f"{path}: not a valid JSON camera profile: {e}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ProfileError(f"{path}: not an nrhdr camera profile (field 'format' must be '{FORMAT}')")
    ver = doc.get("version")
    if ver != VERSION:
        raise ProfileError(f"{path}: field 'version': this nrhdr reads version {VERSION}, file has {ver!r}")
    for k in ("mask", "nd", "width", "height"):
        if k not in doc:
            raise ProfileError(f"{path}: missing required field '{k}'")
    mask_path = path.parent / str(doc["mask"])
    try:
        mask = io.read_mask(mask_path)
    except io.ImageFileError as e:
        raise ProfileError(f"{path}: field 'mask': {e}") from None
    if mask.shape != (doc["height"], doc["width"]):
        raise ProfileError(f"{path}: field 'mask': {mask_path.name} is {mask.shape[1]}x{mask.shape[0]} "
                           f"but the profile says {doc['width']}x{doc['height']}")
    fields = {}
    for k, typ in _SCALARS.items():
        if k in doc:
            v = doc[k]
            if typ is int and not (isinstance(v, int) and not isinstance(v, bool)):
                raise ProfileError(f"{path}: field '{k}' must be an integer, got {v!r}")
            if typ is float and not (isinstance(v, (int, float)) and not isinstance(v, bool)):
                raise ProfileError(f"{path}: field '{k}' must be a number, got {v!r}")
            if typ is str and not isinstance(v, str):
                raise ProfileError(f"{path}: field '{k}' must be a string, got {v!r}")
            fields[k] = typ(v)
    xt = None
    xt_file = None
    if doc.get("crosstalk") is not None:
        from . import crosstalk
        try:
            xt = crosstalk.load_calibration(doc["crosstalk"], path.parent, mask.shape)
        except (OSError, ValueError, KeyError) as e:
            raise ProfileError(f"{path}: field 'crosstalk': {e}") from None
        xt_file = doc["crosstalk"].get("file") if isinstance(doc["crosstalk"], dict) else None
    p = CameraProfile(mask=mask, crosstalk=xt, crosstalk_file=xt_file, extra=doc.get("extra", {}),
                      path=path, **fields)
    validate(p, where=str(path))
    return p


def default(height: int = 480, width: int = 640, seed: int = 0, pattern: str = "nonregular",
            **fields) -> CameraProfile:
    """A profile like the paper's prototype: 12 bit, clip at 4094, ND 6.35, half the pixels attenuated."""
    from . import mask as masks
    return make(masks.make_mask(pattern, height, width, seed=seed), **fields)
