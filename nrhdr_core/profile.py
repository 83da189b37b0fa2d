"""Camera profile: one versioned JSON file describing a non-regular ND sensor (docs/PROFILE.md).

The JSON names the ND mask (an 8-bit PNG beside it, 255 = attenuated), optionally a defect-pixel map (an 8-bit
PNG, 0 = good, `DEFECT_HOT` / `DEFECT_DEAD` / `DEFECT_STUCK`) and, once calibrated, the crosstalk calibration
(an .npz beside it, see `crosstalk.py` / `calibration.py`). It says what the sensor's data are: bit depth,
alignment in 16-bit words, packing, black and white level. `load` validates everything and raises
`ProfileError` naming the file and the field at fault.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import numbers
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from . import cfa as cfas
from . import io

FORMAT = "nrhdr-camera-profile"
VERSION = 3                 # the newest version `save` writes: the lowest version that holds the profile's fields
VERSIONS = (1, 2, 3)        # versions `load` reads
# fields a version-1 file cannot hold: an older reader would ignore them and misread the data
V2_FIELDS = ("white_level", "alignment", "packing", "out_of_range", "defects")
# fields of a colour sensor (docs/COLOUR.md): a version-1 or -2 reader would read a Bayer mosaic as grey
V3_FIELDS = ("cfa", "white_balance")

# defect-pixel map values (`CameraProfile.defects`): 0 = good
DEFECT_HOT = 1
DEFECT_DEAD = 2
DEFECT_STUCK = 3
DEFECT_NAMES = {DEFECT_HOT: "hot", DEFECT_DEAD: "dead", DEFECT_STUCK: "stuck"}

ALIGNMENTS = ("lsb", "msb")     # where a bit_depth-bit code sits in its 16-bit word
# packed formats (GenICam PFNC / GigE Vision names): bits per pixel; lines are not padded
PACKINGS = {"none": 16, "mono12packed": 12, "mono12p": 12, "mono10p": 10}
OUT_OF_RANGE = ("clip", "error")  # codes above the bit depth's range: clipped pixels, or an error
# the paper's ADC: 12 bit, white 4095, clip code DN_max = 4095 - 1 (section 2.3)
DEFAULT_WHITE = 4095


class ProfileError(ValueError):
    """A camera profile is missing, unreadable or inconsistent; the message names file and field."""


class ProfileWarning(UserWarning):
    """A profile loads but something cannot be checked (e.g. a calibration without mask checksum)."""


# Bounds beyond which the chain cannot work (docs/PROFILE.md, "Bounds"): a larger ND leaves the regular pixels
# in the bottom 10 % of the display (log tone mapping, white = clip * ND) and the white overflows float32
# arithmetic long before 1e308; gain, full well and noise outside these ranges describe no real sensor.
ND_MAX = 1024.0             # 10 stops
GAIN_RANGE = (1e-4, 1e4)    # DN per electron
FULL_WELL_RANGE = (1.0, 1e9)  # electrons
READ_NOISE_MAX = 1e6        # electrons rms
MAX_SIZE = 65536            # width, height in pixels


def mask_sha256(mask: np.ndarray) -> str:
    """Checksum binding a calibration to its sensor: sha256 of 'HxW:' and the mask bits (row-major,
    np.packbits, 1 = attenuated)."""
    m = np.ascontiguousarray(np.asarray(mask, dtype=bool))
    h = hashlib.sha256(f"{m.shape[0]}x{m.shape[1]}:".encode())
    h.update(np.packbits(m, axis=None).tobytes())
    return h.hexdigest()


def implied_white_level(clip_code: int, bit_depth: int) -> int:
    """The white level a profile without one has: clip_code + 1, at most the ADC's largest code."""
    return min(int(clip_code) + 1, (1 << bit_depth) - 1)


@dataclasses.dataclass(frozen=True, eq=False)
class CameraProfile:
    """A sensor with a non-regular ND mask (paper section 2.3). Codes are `bit_depth`-bit ADC values.

    `white_level` and `clip_code` follow each other when only one is given: clip_code = white_level - 1
    (the paper's DN_max = 4095 - 1); neither given: the paper's 4095 / 4094."""
    mask: np.ndarray                  # bool (H, W), True = attenuated
    nd: float = 6.35                  # ND factor, Eq. 1 (paper's prototype: ~6.35)
    bit_depth: int = 12
    clip_code: int | None = None      # codes >= clip_code are clipped (None: white_level - 1)
    black_level: float = 0.0          # code of zero light
    white_level: int | None = None    # code a saturated pixel reads (None: clip_code + 1, at most the ADC's max)
    alignment: str = "lsb"            # "lsb": code = word; "msb": code = word >> (16 - bit_depth)
    packing: str = "none"             # PACKINGS: "none" = one 16-bit word per pixel
    out_of_range: str = "clip"        # a code above the bit depth's range: "clip" (clipped pixel) or "error"
    defects: np.ndarray | None = None  # uint8 (H, W): 0 good, DEFECT_HOT / DEFECT_DEAD / DEFECT_STUCK
    cfa: str = "none"                 # colour filter array: "none" (monochrome) or a Bayer phase (cfa.PATTERNS)
    white_balance: tuple = (1.0, 1.0, 1.0)  # R, G, B gains that make a grey object grey (colour sensors)
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

    def __post_init__(self):
        cc, wl = self.clip_code, self.white_level
        ints = all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (cc, wl) if v is not None)
        if ints and cc is None:
            cc = DEFAULT_WHITE - 1 if wl is None else int(wl) - 1
        if ints and wl is None and isinstance(self.bit_depth, int) and 1 <= self.bit_depth <= 16:
            wl = implied_white_level(cc, self.bit_depth)
        object.__setattr__(self, "clip_code", cc)
        object.__setattr__(self, "white_level", wl)
        d = self.defects
        # the defect pixels as flat indices: classify's defect pass visits only these (none: no cost)
        idx = np.flatnonzero(d) if isinstance(d, np.ndarray) and d.ndim == 2 else np.zeros(0, np.int64)
        object.__setattr__(self, "defect_index", idx.astype(np.int64))

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

    @property
    def packed_bits(self) -> int:
        """Bits per pixel in the frame buffer: 16 unpacked, else the packing's."""
        return PACKINGS.get(self.packing, 16)

    def frame_bytes(self) -> int:
        """Bytes of one frame as the source sends it: 2 per pixel unpacked, else the packing's bit stream
        (lines not padded) rounded up to a whole byte."""
        return (self.width * self.height * self.packed_bits + 7) // 8

    def replace(self, **changes) -> "CameraProfile":
        """A copy with `changes`; a new clip code or bit depth re-derives the white level, a new white level
        the clip code, unless given too."""
        if "white_level" not in changes and ("clip_code" in changes or "bit_depth" in changes):
            changes["white_level"] = None
        if "white_level" in changes and "clip_code" not in changes:
            changes["clip_code"] = None
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
    if max(m.shape) > MAX_SIZE:
        bad("mask", f"{m.shape[1]}x{m.shape[0]} is larger than {MAX_SIZE} pixels on a side")
    for f in ("nd", "gain", "full_well", "read_noise", "black_level", "l_min"):
        v = getattr(p, f)
        if not (isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)):
            bad(f, f"must be a finite number, got {v!r}")
    for f in ("bit_depth", "clip_code"):
        v = getattr(p, f)
        if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool)):
            bad(f, f"must be an integer, got {v!r}")
    if not (isinstance(p.bit_depth, int) and 1 <= p.bit_depth <= 16):
        bad("bit_depth", f"must be an integer 1..16, got {p.bit_depth!r}")
    if not (isinstance(p.white_level, (int, np.integer)) and not isinstance(p.white_level, bool)):
        bad("white_level", f"must be an integer, got {p.white_level!r}")
    if not (1 <= p.nd <= ND_MAX):
        bad("nd", f"must be in 1..{ND_MAX:g} (attenuation factor; above {ND_MAX:g} = 10 stops the regular "
                  f"pixels would tone-map to black), got {p.nd!r}")
    if not (GAIN_RANGE[0] <= p.gain <= GAIN_RANGE[1]):
        bad("gain", f"must be in {GAIN_RANGE[0]:g}..{GAIN_RANGE[1]:g} DN per electron, got {p.gain!r}")
    if not (FULL_WELL_RANGE[0] <= p.full_well <= FULL_WELL_RANGE[1]):
        bad("full_well", f"must be in {FULL_WELL_RANGE[0]:g}..{FULL_WELL_RANGE[1]:g} electrons, "
                         f"got {p.full_well!r}")
    if p.read_noise > READ_NOISE_MAX:
        bad("read_noise", f"must be <= {READ_NOISE_MAX:g} electrons, got {p.read_noise!r}")
    if not (0 < p.white_level <= p.max_code):
        bad("white_level", f"must be in 1..{p.max_code} for {p.bit_depth}-bit data, got {p.white_level}")
    if not (0 < p.clip_code <= p.white_level):
        bad("clip_code", f"must be in 1..white_level ({p.white_level}) for {p.bit_depth}-bit data, "
                         f"got {p.clip_code}")
    if not (0 <= p.black_level < p.clip_code):
        bad("black_level", f"must be in 0..clip_code-1, got {p.black_level}")
    if not (p.read_noise >= 0):
        bad("read_noise", f"must be >= 0, got {p.read_noise}")
    sat = p.full_well * p.gain + p.black_level
    if sat < p.clip_code + 3.0 * p.read_noise * p.gain:
        bad("gain", f"full_well * gain + black_level = {sat:.1f} DN does not reach clip_code "
                    f"{p.clip_code} by 3 sigma of read noise: saturated pixels would read as valid")
    if not (0 <= p.l_min < p.clip_code - p.black_level):
        bad("l_min", f"must be in 0..clip_code-black_level, got {p.l_min}")
    if not isinstance(p.name, str):
        bad("name", f"must be a string, got {p.name!r}")
    _validate_format(p, bad)
    if not isinstance(p.extra, dict):
        bad("extra", f"must be an object, got {type(p.extra).__name__}")


def _validate_format(p: CameraProfile, bad) -> None:
    """The data format fields: alignment, packing (its bit depth, LSB only), out_of_range, defects."""
    if p.alignment not in ALIGNMENTS:
        bad("alignment", f"must be one of {', '.join(ALIGNMENTS)}, got {p.alignment!r}")
    if p.packing not in PACKINGS:
        bad("packing", f"must be one of {', '.join(PACKINGS)}, got {p.packing!r}")
    if p.packing != "none":
        if p.bit_depth != PACKINGS[p.packing]:
            bad("packing", f"{p.packing} holds {PACKINGS[p.packing]}-bit codes but bit_depth is {p.bit_depth}")
        if p.alignment != "lsb":
            bad("alignment", f"packed data ({p.packing}) are unpacked to LSB-aligned codes: alignment must be "
                             f"'lsb', got {p.alignment!r}")
    if p.out_of_range not in OUT_OF_RANGE:
        bad("out_of_range", f"must be one of {', '.join(OUT_OF_RANGE)}, got {p.out_of_range!r}")
    if p.cfa not in cfas.CFAS:
        bad("cfa", f"must be one of {', '.join(cfas.CFAS)}, got {p.cfa!r}")
    wb = p.white_balance
    if not (isinstance(wb, tuple) and len(wb) == 3 and all(
            isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) and 1e-3 <= v <= 1e3
            for v in wb)):
        bad("white_balance", f"must be three finite gains (R, G, B) in 0.001..1000, got {wb!r}")
    if p.cfa != cfas.NONE and (p.height % 2 or p.width % 2):
        bad("cfa", f"a Bayer sensor has an even width and height (whole 2 x 2 blocks), the mask is "
                   f"{p.width}x{p.height}")
    d = p.defects
    if d is None:
        return
    if not isinstance(d, np.ndarray) or d.dtype != np.uint8 or d.shape != p.mask.shape:
        what = f"{d.dtype} {d.shape}" if isinstance(d, np.ndarray) else type(d).__name__
        bad("defects", f"must be None or a uint8 array of the mask's shape {p.mask.shape}, got {what}")
    wrong = _defect_values_error(d)
    if wrong:
        bad("defects", wrong)


def _defect_values_error(d: np.ndarray) -> str | None:
    """What is wrong with the values of a defect map, or None."""
    if not d.size or int(d.max()) <= DEFECT_STUCK:
        return None
    return (f"values must be 0 (good), {DEFECT_HOT} (hot), {DEFECT_DEAD} (dead) or {DEFECT_STUCK} (stuck); "
            f"{int(np.sum(d > DEFECT_STUCK))} pixels hold others (largest {int(d.max())})")


def make(mask: np.ndarray, defects: np.ndarray | None = None, **fields) -> CameraProfile:
    """A validated profile for `mask` (bool (H, W), True = attenuated); `defects`: None or an integer
    (H, W) map (0 good, DEFECT_HOT, DEFECT_DEAD, DEFECT_STUCK), stored as uint8."""
    if defects is not None:
        d = np.asarray(defects)
        if d.dtype.kind in "biu" and d.size and 0 <= int(d.min()) and int(d.max()) <= 255:
            defects = np.ascontiguousarray(d, dtype=np.uint8)
    p = CameraProfile(mask=np.asarray(mask, dtype=bool), defects=defects, **fields)
    validate(p)
    return p


def defect_counts(p: CameraProfile) -> dict[str, int]:
    """Number of hot, dead and stuck pixels of the profile's defect map (zeros without one)."""
    d = p.defects
    return {name: (0 if d is None else int(np.count_nonzero(d == v))) for v, name in DEFECT_NAMES.items()}


_SCALARS = {"nd": float, "bit_depth": int, "clip_code": int, "black_level": float, "gain": float,
            "read_noise": float, "full_well": float, "l_min": float, "name": str}
# version-2 scalars (a version-2 file always states white_level; the others when not their default)
_V2_SCALARS = {"white_level": int, "alignment": str, "packing": str, "out_of_range": str}


def written_files(path) -> list[Path]:
    """The files `save(p, path)` may write: the JSON, `<stem>_mask.png`, `<stem>_crosstalk.npz`,
    `<stem>_defects.png`."""
    path = Path(path)
    return [path, path.with_name(f"{path.stem}_mask.png"), path.with_name(f"{path.stem}_crosstalk.npz"),
            path.with_name(f"{path.stem}_defects.png")]


def _v2_values(p: CameraProfile) -> dict[str, Any]:
    """The version-2 scalars whose value a version-1 file could not say (white level other than the clip
    code's, MSB alignment, packing, out-of-range errors)."""
    out = {}
    if p.white_level != implied_white_level(p.clip_code, p.bit_depth):
        out["white_level"] = int(p.white_level)
    for k, default in (("alignment", "lsb"), ("packing", "none"), ("out_of_range", "clip")):
        if getattr(p, k) != default:
            out[k] = getattr(p, k)
    return out


def _v3_values(p: CameraProfile) -> dict[str, Any]:
    """The colour fields, when the sensor has a CFA or a white balance other than 1, 1, 1."""
    out: dict[str, Any] = {}
    if p.cfa != cfas.NONE:
        out["cfa"] = p.cfa
    if tuple(p.white_balance) != (1.0, 1.0, 1.0):
        out["white_balance"] = [float(v) for v in p.white_balance]
    return out


def save(p: CameraProfile, path, overwrite: bool = True) -> Path:
    """Write `path` (JSON), the mask PNG, the defect map PNG and the crosstalk calibration beside it,
    atomically; version 1 unless a version-2 field is needed (V2_FIELDS). With
    `overwrite=False` an existing file among them is refused (io.OutputExistsError) before anything is
    written (the `nrhdr` commands pass their `--force` here)."""
    validate(p)
    path = Path(path)
    if not overwrite:
        io.refuse_existing(written_files(path))
    stem = path.stem
    mask_name = f"{stem}_mask.png"
    io.write_mask(path.parent / mask_name, p.mask)
    v2 = _v2_values(p)
    v3 = _v3_values(p)
    version = 3 if v3 else 2 if (v2 or p.defects is not None) else 1
    doc: dict[str, Any] = {"format": FORMAT, "version": version,
                           "width": p.width, "height": p.height, "mask": mask_name}
    for k in _SCALARS:
        doc[k] = getattr(p, k)
    if version >= 2:    # a version-2 or -3 file states its white level
        doc["white_level"] = int(p.white_level)
    doc.update(v2)
    doc.update(v3)
    if p.defects is not None:
        doc["defects"] = f"{stem}_defects.png"
        io.write_image(path.parent / doc["defects"], p.defects, np.uint8)
    doc["crosstalk"] = None
    if p.crosstalk is not None:
        from . import crosstalk
        xt_name = f"{stem}_crosstalk.npz"
        doc["crosstalk"] = crosstalk.save_calibration(p.crosstalk, path.parent / xt_name)
        # bind the calibration to its sensor: the mask it was made with, its size and ADC depth
        doc["crosstalk"].update(mask_sha256=mask_sha256(p.mask), mask_width=p.width, mask_height=p.height,
                                bit_depth=p.bit_depth)
    if p.extra:
        doc["extra"] = p.extra
    _write_json_atomic(path, doc)
    return path


def _write_json_atomic(path: Path, doc: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name("." + path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    os.replace(tmp, path)


def load(path, allow_outside: bool = False) -> CameraProfile:
    """Read and validate a camera profile JSON (docs/PROFILE.md). The files it names (mask, calibration)
    must lie in the profile's folder unless `allow_outside` (io.resolve_named); every value is checked
    before use. Any problem is a ProfileError naming the file and the field."""
    path = Path(path)
    if not path.is_file():
        raise ProfileError(f"{path}: camera profile not found")
    doc = io.read_json(path, "JSON camera profile", error=ProfileError)
    if doc.get("format") != FORMAT:
        raise ProfileError(f"{path}: not an nrhdr camera profile (field 'format' must be '{FORMAT}')")
    ver = doc.get("version")
    if ver not in VERSIONS or isinstance(ver, bool):
        raise ProfileError(f"{path}: field 'version': this nrhdr reads versions "
                           f"{', '.join(map(str, VERSIONS))}, file has {ver!r}")
    for need, late_fields in ((2, V2_FIELDS), (3, V3_FIELDS)):
        late = [k for k in late_fields if k in doc]
        if ver < need and late:
            names = ", ".join(f"'{k}'" for k in late)
            raise ProfileError(f"{path}: field{'s' if len(late) > 1 else ''} {names} need{'' if len(late) > 1 else 's'}"
                               f" version {need} (a version-{ver} reader would ignore them and misread the data); "
                               f"the file says version {ver}")
    for k in ("mask", "nd", "width", "height"):
        if k not in doc:
            raise ProfileError(f"{path}: missing required field '{k}'")
    for k in ("width", "height"):
        v = doc[k]
        if not (isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_SIZE):
            raise ProfileError(f"{path}: field '{k}' must be an integer number of pixels in 1..{MAX_SIZE}, "
                               f"got {v!r}")
    if not isinstance(doc["mask"], str) or not doc["mask"]:
        raise ProfileError(f"{path}: field 'mask' must be the name of a PNG file, got {doc['mask']!r}")
    mask_path = io.resolve_named(path, "mask", doc["mask"], ProfileError, allow_outside)
    try:
        mask = io.read_mask(mask_path, shape=(doc["height"], doc["width"]))
    except io.ImageFileError as e:
        raise ProfileError(f"{path}: field 'mask': {e}") from None
    fields = {}
    for k, typ in {**_SCALARS, **_V2_SCALARS}.items():
        if k in doc:
            v = doc[k]
            if typ is int and not (isinstance(v, int) and not isinstance(v, bool)):
                raise ProfileError(f"{path}: field '{k}' must be an integer, got {v!r}")
            if typ is float and not (isinstance(v, (int, float)) and not isinstance(v, bool)):
                raise ProfileError(f"{path}: field '{k}' must be a number, got {v!r}")
            if typ is str and not isinstance(v, str):
                raise ProfileError(f"{path}: field '{k}' must be a string, got {v!r}")
            try:
                fields[k] = typ(v)
            except OverflowError:
                raise ProfileError(f"{path}: field '{k}' is out of range: {v!r}") from None
    if "cfa" in doc:
        if not isinstance(doc["cfa"], str):
            raise ProfileError(f"{path}: field 'cfa' must be a string, got {doc['cfa']!r}")
        fields["cfa"] = doc["cfa"]
    if "white_balance" in doc:
        wb = doc["white_balance"]
        if not (isinstance(wb, list) and len(wb) == 3
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in wb)):
            raise ProfileError(f"{path}: field 'white_balance' must be a list of three numbers (R, G, B gains), "
                               f"got {wb!r}")
        fields["white_balance"] = tuple(float(v) for v in wb)
    extra = doc.get("extra", {})
    if not isinstance(extra, dict):
        raise ProfileError(f"{path}: field 'extra' must be an object, got {type(extra).__name__}")
    if doc.get("defects") is not None:
        fields["defects"] = _read_defects(path, doc["defects"], mask.shape, allow_outside)
    # the sensor's own fields first: a calibration is checked against a valid sensor
    validate(CameraProfile(mask=mask, extra=extra, path=path, **fields), where=str(path))
    xt = None
    xt_file = None
    if doc.get("crosstalk") is not None:
        from . import crosstalk
        entry = doc["crosstalk"]
        if not isinstance(entry, dict):
            raise ProfileError(f"{path}: field 'crosstalk' must be an object or null, got {type(entry).__name__}")
        _check_binding(path, entry, mask, mask_path, fields.get("bit_depth", CameraProfile.bit_depth))
        try:
            xt = crosstalk.load_calibration(entry, path.parent, mask.shape, source=path,
                                            allow_outside=allow_outside)
        except (OSError, ValueError, KeyError, TypeError, IndexError, AttributeError) as e:
            raise ProfileError(f"{path}: field 'crosstalk': {e}") from None
        xt_file = entry.get("file")
        _check_calibration_fits(path, xt, fields)
    p = CameraProfile(mask=mask, crosstalk=xt, crosstalk_file=xt_file, extra=extra, path=path, **fields)
    validate(p, where=str(path))
    return p


def _read_defects(path: Path, name, shape, allow_outside: bool) -> np.ndarray:
    """The defect map the profile names: an 8-bit one-channel PNG in the profile's folder, of the mask's size
    (checked before decoding), values 0..DEFECT_STUCK."""
    if not isinstance(name, str) or not name:
        raise ProfileError(f"{path}: field 'defects' must be the name of a PNG file or null, got {name!r}")
    dpath = io.resolve_named(path, "defects", name, ProfileError, allow_outside)
    oiio = io._oiio()

    def check(spec):
        if int(spec.nchannels) != 1 or spec.format.basetype != oiio.UINT8:
            raise io.ImageFileError(f"{dpath}: a defect map must be a one-channel 8-bit image, got "
                                    f"{int(spec.nchannels)} channels of {spec.format}")
    try:
        px = io._read_pixels(dpath, lambda spec: oiio.UINT8, shape, check=check)[0]
    except io.ImageFileError as e:
        raise ProfileError(f"{path}: field 'defects': {e}") from None
    d = np.ascontiguousarray(px[:, :, 0], dtype=np.uint8)
    wrong = _defect_values_error(d)
    if wrong:
        raise ProfileError(f"{path}: field 'defects': {dpath.name}: {wrong}")
    return d


def _check_calibration_fits(path: Path, xt, fields: dict) -> None:
    """The calibration's ADC levels must be the profile's: its clip code within the ADC range, its black
    level below its clip code (its LUT maps codes above that black level)."""
    bits = fields.get("bit_depth", CameraProfile.bit_depth)
    max_code = (1 << bits) - 1
    if not (1 <= xt.nd <= ND_MAX):
        raise ProfileError(f"{path}: field 'crosstalk.nd': must be in 1..{ND_MAX:g}, got {xt.nd!r}")
    if not (0 < xt.clip_code <= max_code):
        raise ProfileError(f"{path}: field 'crosstalk.clip_code': must be in 1..{max_code} for {bits}-bit data, "
                           f"got {xt.clip_code}")
    if not (0 <= xt.black_level < xt.clip_code):
        raise ProfileError(f"{path}: field 'crosstalk.black_level': must be in 0..clip_code-1, got "
                           f"{xt.black_level}")


def _check_binding(path: Path, entry: dict, mask: np.ndarray, mask_path: Path, bit_depth: int) -> None:
    """A calibration belongs to the sensor it was measured on: its recorded mask checksum, size and bit depth
    must match the profile's mask (docs/PROFILE.md). Calibrations that record no checksum load
    with a ProfileWarning (nothing to compare)."""
    xt = entry.get("file")
    want = entry.get("mask_sha256")
    if want is None:
        warnings.warn(f"{path}: field 'crosstalk': calibration {xt} records no mask checksum: cannot check "
                      f"that it was made for {mask_path.name}; re-save the profile (profile.save) to bind it",
                      ProfileWarning, stacklevel=3)
        return
    if not isinstance(want, str):
        raise ProfileError(f"{path}: field 'crosstalk.mask_sha256' must be a string, got {want!r}")
    size = (entry.get("mask_width"), entry.get("mask_height"))
    if size != (mask.shape[1], mask.shape[0]):
        raise ProfileError(f"{path}: field 'crosstalk': calibration {xt} was made for a {size[0]}x{size[1]} "
                           f"mask, but {mask_path.name} is {mask.shape[1]}x{mask.shape[0]}")
    if entry.get("bit_depth") != bit_depth:
        raise ProfileError(f"{path}: field 'crosstalk': calibration {xt} was made for {entry.get('bit_depth')!r}"
                           f"-bit data, the profile says {bit_depth}-bit")
    got = mask_sha256(mask)
    if got != want:
        raise ProfileError(f"{path}: field 'crosstalk': calibration {xt} was made for another sensor: its mask "
                           f"checksum {want[:12]}... differs from {mask_path.name} ({got[:12]}...); "
                           f"recalibrate with this mask (nrhdr calibrate) or use the mask it was made with")


def check_same_sensor(calibrated: CameraProfile, stream: CameraProfile) -> None:
    """Raise ProfileError naming both files when `calibrated` (the profile whose crosstalk calibration is
    applied) describes another sensor than `stream` (the profile the raw frames were classified with):
    different mask size, mask pattern (checksum) or bit depth."""
    a = calibrated.path or calibrated.name
    b = stream.path or stream.name
    if calibrated.mask.shape != stream.mask.shape:
        raise ProfileError(f"calibration profile {a} has a {calibrated.width}x{calibrated.height} mask but the "
                           f"stream's profile {b} has {stream.width}x{stream.height}")
    if calibrated.bit_depth != stream.bit_depth:
        raise ProfileError(f"calibration profile {a} is for {calibrated.bit_depth}-bit data but the stream's "
                           f"profile {b} says {stream.bit_depth}-bit")
    ha, hb = mask_sha256(calibrated.mask), mask_sha256(stream.mask)
    if ha != hb:
        raise ProfileError(f"calibration profile {a} was made for another sensor than the stream's profile {b}: "
                           f"their ND masks differ ({int(np.sum(calibrated.mask != stream.mask))} pixels, "
                           f"checksums {ha[:12]}... vs {hb[:12]}...)")


def default(height: int = 480, width: int = 640, seed: int = 0, pattern: str = "nonregular",
            nd_layout: str | None = None, **fields) -> CameraProfile:
    """A profile like the paper's prototype: 12 bit, clip at 4094, ND 6.35, half the pixels attenuated. With a
    Bayer `cfa` (in `fields`) the mask is `mask.cfa_mask(pattern, ..., nd_layout)` (default
    `mask.DEFAULT_ND_LAYOUT`); a monochrome sensor takes no `nd_layout` but `independent`."""
    from . import mask as masks
    if cfas.is_colour(fields.get("cfa", cfas.NONE)):
        m = masks.cfa_mask(pattern, height, width, nd_layout or masks.DEFAULT_ND_LAYOUT, seed=seed)
        return make(m, **fields)
    if nd_layout not in (None, "independent"):
        masks.check_nd_layout(nd_layout)
        raise ValueError(f"nd_layout: {nd_layout!r} places the ND filter over a colour filter array; a "
                         f"monochrome sensor (cfa none) has the layout 'independent'")
    return make(masks.make_mask(pattern, height, width, seed=seed), **fields)
