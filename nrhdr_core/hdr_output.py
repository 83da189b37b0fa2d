"""HDR10 / HLG delivery metadata (docs/HDR-OUTPUT.md): the SMPTE ST 2086 mastering display and the CTA-861.3
content light levels (MaxCLL, MaxFALL) measured from the 10-bit codes a clip is encoded with, their text forms
(the `mastering-display-info` / `content-light-level` caps fields of GStreamer video caps and x265's options),
and the encoder settings chosen by measurement (docs/BENCHMARKS.md, "HDR10 encoding"); the Y'CbCr frames the
encoder is given; and the measurement of an encode (`nrhdr hdr10 --report`, docs/HDR-OUTPUT.md "Measuring an
encode"): the display light before quantisation, a player's R'G'B' of decoded 4:2:0 and the scores.

Codes are BT.2100 10-bit narrow range (64..940), as `tonemap.hdr_encode` writes them (<< 6 in uint16).
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
from numba import njit, prange

from .tonemap import (HLG_NOMINAL_PEAK, HLG_SYSTEM_GAMMA, L_P, LUMA_BT709, LUMA_BT2020, REFERENCE_WHITE_NITS,
                      RGB_PRIMARIES, TRANSFERS, WHITE_D65, eotf_inverse_ST2084, eotf_ST2084, oetf_HLG,
                      oetf_inverse_HLG, peak_luminance)

# CIE 1931 xy of the mastering display primaries (R, G, B): BT.2020 (ITU-R BT.2020 Table 3), P3-D65 (SMPTE
# EG 432-1); D65 white
PRIMARIES = {
    "bt2020": RGB_PRIMARIES["bt2020"],
    "p3": ((0.680, 0.320), (0.265, 0.690), (0.150, 0.060)),
}
DEFAULT_PEAK = 1000.0            # cd/m^2: the mastering display (and the EETF's target)
DEFAULT_MIN_LUMINANCE = 0.005    # cd/m^2: the mastering display's black
CHROMA_UNIT = 50000              # ST 2086 / H.265 D.3.28: chromaticity in 0.00002
LUMINANCE_UNIT = 10000           # ST 2086: luminance in 0.0001 cd/m^2
# x265's constant quality (crf) chosen by measurement (docs/BENCHMARKS.md "HDR10 encoding") and its speed
DEFAULT_CRF = 16
DEFAULT_SPEED_PRESET = "medium"
MIN_ENCODE_WIDTH = 64      # pixels: one HEVC coding tree unit (x265's default CTU size)
SPEED_PRESETS = ("ultrafast", "superfast", "veryfast", "faster", "fast", "medium", "slow", "slower",
                 "veryslow", "placebo")
CONTAINERS = {".mp4": "mp4", ".mkv": "mkv"}
# GStreamer 1.22's matroskamux writes the mastering luminance divided by 5 (docs/HDR-OUTPUT.md): the caps
# handed to it carry the luminance times this factor, so that the container says what the stream's SEI says.
MATROSKA_LUMINANCE_FACTOR = 5


def container_of(path) -> str | None:
    """'mp4' or 'mkv' from the file name's suffix (case-insensitive); None for anything else."""
    return CONTAINERS.get(Path(path).suffix.lower())


@dataclasses.dataclass(frozen=True)
class MasteringDisplay:
    """SMPTE ST 2086 mastering display colour volume: primaries (a PRIMARIES name), D65 white, luminance
    range in cd/m^2."""
    primaries: str = "bt2020"
    max_luminance: float = DEFAULT_PEAK
    min_luminance: float = DEFAULT_MIN_LUMINANCE

    def __post_init__(self):
        if self.primaries not in PRIMARIES:
            raise ValueError(f"mastering display primaries must be one of {', '.join(PRIMARIES)}, "
                             f"got {self.primaries!r}")
        if not (0 < self.max_luminance <= L_P and 0 <= self.min_luminance < self.max_luminance):
            raise ValueError(f"mastering display luminance must satisfy 0 <= min < max <= {L_P:g} cd/m^2, got "
                             f"min {self.min_luminance}, max {self.max_luminance}")

    def units(self) -> tuple[list[int], list[int], int, int]:
        """([Rx, Ry, Gx, Gy, Bx, By], [Wx, Wy]) in 0.00002 and (Lmax, Lmin) in 0.0001 cd/m^2, as coded."""
        xy = [round(c * CHROMA_UNIT) for p in PRIMARIES[self.primaries] for c in p]
        wp = [round(c * CHROMA_UNIT) for c in WHITE_D65]
        return xy, wp, round(self.max_luminance * LUMINANCE_UNIT), round(self.min_luminance * LUMINANCE_UNIT)

    def caps_field(self, luminance_factor: int = 1) -> str:
        """GStreamer's `mastering-display-info`: Rx:Ry:Gx:Gy:Bx:By:Wx:Wy:Lmax:Lmin (R, G, B order);
        `luminance_factor` scales Lmax and Lmin (MATROSKA_LUMINANCE_FACTOR for the muxer's caps)."""
        xy, wp, lmax, lmin = self.units()
        return ":".join(str(x) for x in xy + wp + [lmax * luminance_factor, lmin * luminance_factor])

    def x265(self) -> str:
        """x265's `master-display`: G(x,y)B(x,y)R(x,y)WP(x,y)L(max,min) (G, B, R order)."""
        (rx, ry, gx, gy, bx, by), (wx, wy), lmax, lmin = self.units()
        return f"G({gx},{gy})B({bx},{by})R({rx},{ry})WP({wx},{wy})L({lmax},{lmin})"


def code_luminance(transfer: str = "pq") -> np.ndarray:
    """Display light (cd/m^2) of each 10-bit narrow-range code 0..1023 (codes outside 64..940 clamp):
    pq: the ST 2084 EOTF; hlg: the BT.2100 reference OOTF on the 1000 cd/m^2 display, L = 1000 E^1.2
    (grey: R = G = B)."""
    return code_light(np.arange(1024), transfer)


def _check_transfer(transfer: str) -> None:
    if transfer not in TRANSFERS:
        raise ValueError(f"HDR transfer must be one of {', '.join(TRANSFERS)}, got {transfer!r}")


def code_light(codes, transfer: str = "pq") -> np.ndarray:
    """Display light (cd/m^2, float64) of 10-bit narrow-range code values, whole or fractional (a decoder's
    R'G'B'), as `code_luminance` gives it for whole codes: pq the ST 2084 EOTF, hlg the 1000 cd/m^2 reference
    display's L = 1000 E^1.2 of the channel (the grey OOTF); codes outside 64..940 clamp."""
    _check_transfer(transfer)
    sig = np.clip((np.asarray(codes, np.float64) - 64.0) / 876.0, 0.0, 1.0)
    if transfer == "pq":
        return eotf_ST2084(sig)
    return HLG_NOMINAL_PEAK * oetf_inverse_HLG(sig) ** HLG_SYSTEM_GAMMA


def light_code(light, transfer: str = "pq") -> np.ndarray:
    """The exact (unrounded) 10-bit narrow-range code of display light (cd/m^2): the inverse of `code_light`,
    64 + 876 E' (BT.2100 Table 9) with E' the ST 2084 inverse EOTF (pq) or the HLG OETF of (L / 1000)^(1/1.2)."""
    _check_transfer(transfer)
    L = np.maximum(np.nan_to_num(np.asarray(light, np.float64), nan=0.0), 0.0)
    if transfer == "pq":
        sig = eotf_inverse_ST2084(L)
    else:
        sig = oetf_HLG((np.minimum(L, HLG_NOMINAL_PEAK) / HLG_NOMINAL_PEAK) ** (1.0 / HLG_SYSTEM_GAMMA))
    return 64.0 + 876.0 * sig


class LightLevels:
    """CTA-861.3 content light levels of a sequence of frames of 10-bit codes: MaxCLL = the brightest pixel's
    light, MaxFALL = the largest frame-average light, a pixel's light being max(R, G, B) (grey frames: its
    luminance), both in cd/m^2 rounded up. `update(codes, shift=6)` takes one frame (uint16 codes << shift,
    grey (H, W) or R'G'B' (3, H, W))."""

    def __init__(self, transfer: str = "pq"):
        self.lut = code_luminance(transfer)
        self.frames = 0
        self.max_code = 0
        self.max_fall = 0.0

    def update(self, codes: np.ndarray, shift: int = 6) -> None:
        c = np.asarray(codes)
        if c.ndim == 3:
            c = c.max(axis=0)     # the codes are monotonic in light: the largest code is max(R, G, B)'s
        hist = np.bincount((c >> shift).ravel(), minlength=1024)[:1024]
        if c.size == 0:
            return
        self.max_code = max(self.max_code, int(np.flatnonzero(hist).max()))
        self.max_fall = max(self.max_fall, float(hist @ self.lut) / c.size)
        self.frames += 1

    @property
    def max_cll(self) -> int:
        return int(math.ceil(self.lut[self.max_code] - 1e-9)) if self.frames else 0

    @property
    def max_fall_int(self) -> int:
        return int(math.ceil(self.max_fall - 1e-9)) if self.frames else 0

    def values(self) -> tuple[int, int]:
        """(MaxCLL, MaxFALL) in whole cd/m^2."""
        return self.max_cll, self.max_fall_int


def estimate_light_levels(white: float, diffuse_white: float, transfer: str = "pq",
                          reference_white: float = REFERENCE_WHITE_NITS, exposure_stops: float = 0.0,
                          peak: float = DEFAULT_PEAK) -> tuple[int, int]:
    """(MaxCLL, MaxFALL) for live work, where the frames are not known in advance: MaxCLL = the brightest
    light the mapping can give (the sensor's white through `hdr_encode`, at most `peak` when the EETF rolls
    it off); MaxFALL = the reference white (a frame averaging at the diffuse white: an upper estimate for
    ordinary scenes, BT.2408), at most MaxCLL."""
    top = peak_luminance(white, diffuse_white, transfer, reference_white, exposure_stops)
    if peak > 0:
        top = min(top, peak)
    if transfer == "hlg":
        top = min(top, HLG_NOMINAL_PEAK)
    cll = int(math.ceil(top))
    return cll, int(min(math.ceil(reference_white), cll))


def content_light_caps_field(max_cll: int, max_fall: int) -> str:
    """GStreamer's `content-light-level`: MaxCLL:MaxFALL in cd/m^2."""
    if not (0 <= max_fall <= max_cll <= 65535):
        raise ValueError(f"content light levels must satisfy 0 <= MaxFALL <= MaxCLL <= 65535 cd/m^2, got "
                         f"MaxCLL {max_cll}, MaxFALL {max_fall}")
    return f"{int(max_cll)}:{int(max_fall)}"


def i420_10_frame(codes: np.ndarray, out: np.ndarray, offsets, strides, shift: int = 6) -> np.ndarray:
    """Grey 10-bit codes (H, W) (<< shift) into one I420_10LE frame `out` (uint8, the frame's bytes) with the
    planes at byte `offsets` and row `strides` (Y, U, V; GStreamer's VideoInfo): Y = the codes, U and V
    (ceil(W/2) x ceil(H/2)) the neutral 512."""
    h, w = codes.shape
    cw, ch = (w + 1) // 2, (h + 1) // 2
    out[:] = 0
    for plane, (ph, pw) in enumerate(((h, w), (ch, cw), (ch, cw))):
        rows = np.ndarray((ph, pw), np.dtype("<u2"), out, offsets[plane], (strides[plane], 2))
        if plane == 0:
            np.right_shift(codes, shift, out=rows, casting="unsafe")
        else:
            rows[...] = 512
    return out


@njit(cache=True, nogil=True, inline="always")
def _ycc(codes, y, x, kr, kb, shift):
    """(Y', Cb, Cr) of the R'G'B' codes at (y, x): E' = (code - 64) / 876, Y' = G' + Kr (R' - G') + Kb (B' - G')
    (exactly G' for grey), Cb = (B' - Y') / (2 - 2 Kb), Cr = (R' - Y') / (2 - 2 Kr) (ITU-R BT.2020 Table 4)."""
    r = ((codes[0, y, x] >> shift) - 64.0) / 876.0
    g = ((codes[1, y, x] >> shift) - 64.0) / 876.0
    b = ((codes[2, y, x] >> shift) - 64.0) / 876.0
    yy = g + kr * (r - g) + kb * (b - g)
    return yy, (b - yy) / (2.0 - 2.0 * kb), (r - yy) / (2.0 - 2.0 * kr)


@njit(cache=True, nogil=True, inline="always")
def _chroma_code(c):
    code = int(math.floor(512.0 + 896.0 * c + 0.5))
    return min(max(code, 64), 960)


@njit(cache=True, nogil=True, inline="always")
def _put(out, offset, value):
    """A 16-bit little-endian word at byte `offset` of the frame's bytes."""
    out[offset] = np.uint8(value & 0xFF)
    out[offset + 1] = np.uint8(value >> 8)


@njit(cache=True, nogil=True, inline="always")
def _ycc_row(codes, y, kr, kb, shift, out, offset, yrow, cbuf, crbuf):
    """Row y: Y' codes (into `out` at `offset` when `yrow`) and the float Cb, Cr of each pixel into `cbuf`,
    `crbuf`."""
    for x in range(codes.shape[2]):
        yy, cb, cr = _ycc(codes, y, x, kr, kb, shift)
        cbuf[x] = cb
        crbuf[x] = cr
        if yrow:
            code = int(math.floor(64.0 + 876.0 * yy + 0.5))
            _put(out, offset + 2 * x, min(max(code, 4), 1019))


@njit(cache=True, nogil=True, parallel=True)
def _ycbcr_kernel(codes, kr, kb, shift, out, offsets, strides, ch, cw):
    """R'G'B' codes (3, H, W) -> 10-bit narrow-range Y' (H, W) and Cb, Cr planes (ch x cw) as little-endian
    words at byte `offsets` with row `strides` in the frame's bytes `out`: full size, or (4:2:0) sited as
    HEVC's default chroma location (type 0: horizontally co-sited, vertically between the rows): Cb, Cr of
    rows 2i and 2i + 1 averaged, filtered [1, 2, 1] / 4 along the row. One chroma row (and its one or two
    luma rows) at a time, each pixel's Y'CbCr computed once."""
    h, w = codes.shape[1:]
    full = ch == h and cw == w
    nch = min(ch, 64)
    for c in prange(nch):
        buf = np.empty((4, w), np.float64)
        for i in range((c * ch) // nch, ((c + 1) * ch) // nch):
            if full:
                _ycc_row(codes, i, kr, kb, shift, out, offsets[0] + i * strides[0], True, buf[0], buf[2])
                for j in range(cw):
                    _put(out, offsets[1] + i * strides[1] + 2 * j, _chroma_code(buf[0, j]))
                    _put(out, offsets[2] + i * strides[2] + 2 * j, _chroma_code(buf[2, j]))
                continue
            y1 = min(2 * i + 1, h - 1)
            _ycc_row(codes, 2 * i, kr, kb, shift, out, offsets[0] + 2 * i * strides[0], True, buf[0], buf[2])
            _ycc_row(codes, y1, kr, kb, shift, out, offsets[0] + y1 * strides[0], y1 > 2 * i, buf[1], buf[3])
            for j in range(cw):
                cb = 0.0
                cr = 0.0
                for r in range(2):
                    for dx, wt in ((-1, 0.125), (0, 0.25), (1, 0.125)):
                        x = min(max(2 * j + dx, 0), w - 1)
                        cb += wt * buf[r, x]
                        cr += wt * buf[2 + r, x]
                _put(out, offsets[1] + i * strides[1] + 2 * j, _chroma_code(cb))
                _put(out, offsets[2] + i * strides[2] + 2 * j, _chroma_code(cr))


MATRICES = {"bt2020": LUMA_BT2020, "bt709": LUMA_BT709}


def ycbcr_frame(codes: np.ndarray, out: np.ndarray, offsets, strides, subsample: bool = True,
                matrix: str = "bt2020", shift: int = 6) -> np.ndarray:
    """R'G'B' 10-bit codes (3, H, W) (<< shift, as `tonemap.hdr_encode_rgb` writes them) into one I420_10LE
    (`subsample`) or Y444_10LE frame `out` (uint8, the frame's bytes) with the planes at byte `offsets` and row
    `strides` (GStreamer's VideoInfo): Y'CbCr of `matrix` (bt2020: BT.2020 non-constant luminance),
    10-bit narrow range (Y' 64 + 876 Y', C 512 + 896 C; BT.2100 Table 9). Grey (R' = G' = B') gives Y' = the
    code and Cb = Cr = 512."""
    if matrix not in MATRICES:
        raise ValueError(f"Y'CbCr matrix must be one of {', '.join(MATRICES)}, got {matrix!r}")
    c = np.asarray(codes)
    if c.ndim != 3 or c.shape[0] != 3 or c.dtype != np.uint16:
        raise ValueError(f"R'G'B' codes must be uint16 (3, H, W), got {c.dtype} {c.shape}")
    h, w = c.shape[1:]
    ch, cw = ((h + 1) // 2, (w + 1) // 2) if subsample else (h, w)
    frame = out
    if not (isinstance(frame, np.ndarray) and frame.ndim == 1 and frame.dtype == np.uint8
            and frame.flags.c_contiguous):
        raise ValueError("the Y'CbCr frame must be the frame's bytes: a 1-D contiguous uint8 array")
    offsets = np.array([int(x) for x in offsets[:3]], np.int64)
    strides = np.array([int(x) for x in strides[:3]], np.int64)
    ends = offsets + strides * (np.array([h, ch, ch]) - 1) + 2 * np.array([w, cw, cw])
    if (strides < 2 * np.array([w, cw, cw])).any() or (offsets < 0).any() or ends.max() > frame.size:
        raise ValueError(f"a {w}x{h} Y'CbCr frame does not fit {frame.size} bytes with plane offsets "
                         f"{offsets.tolist()} and strides {strides.tolist()}")
    kr, kb = MATRICES[matrix]
    _ycbcr_kernel(c, kr, kb, shift, frame, offsets, strides, ch, cw)
    return out


def full_range16(codes: np.ndarray, shift: int = 6) -> np.ndarray:
    """10-bit narrow-range codes (<< shift) -> full-range 16-bit signal words, round(65535 (c - 64) / 876)
    clamped to 0..65535: the code values of an HDR PNG (cICP full range)."""
    c = (np.asarray(codes) >> shift).astype(np.float64)
    return np.clip(np.floor((c - 64.0) * (65535.0 / 876.0) + 0.5), 0, 65535).astype(np.uint16)


def display_reference(values: np.ndarray, diffuse_white: float, transfer: str = "pq",
                      reference_white: float = REFERENCE_WHITE_NITS, exposure_stops: float = 0.0,
                      peak: float = 0.0, source_peak: float = 0.0) -> np.ndarray:
    """The display light (cd/m^2, float64) `tonemap.hdr_encode` encodes, before 10-bit quantisation: pq:
    display_luminance, hlg: the 1000 cd/m^2 reference display's L = 1000 E^1.2 (E <= 1); then the BT.2390
    EETF to `peak` from `source_peak` (peak > 0). The reference for measuring an encode (`code_luminance` of
    the decoded codes against it)."""
    from .tonemap import display_luminance, eetf_BT2390, hlg_reference_E
    if transfer == "pq":
        L = np.minimum(display_luminance(values, diffuse_white, reference_white, exposure_stops), L_P)
    else:
        E = display_luminance(values, diffuse_white, hlg_reference_E(reference_white), exposure_stops)
        L = HLG_NOMINAL_PEAK * E ** HLG_SYSTEM_GAMMA
    if peak > 0:
        L = eetf_BT2390(L, min(source_peak, L_P), peak)
    return np.minimum(L, HLG_NOMINAL_PEAK) if transfer == "hlg" else L


def display_reference_rgb(rgb: np.ndarray, diffuse_white: float, transfer: str = "pq",
                          white_balance=(1.0, 1.0, 1.0), primaries: str = "bt2020",
                          reference_white: float = REFERENCE_WHITE_NITS, exposure_stops: float = 0.0,
                          peak: float = 0.0, source_peak: float = 0.0) -> np.ndarray:
    """The display light per channel (cd/m^2, float64 (3, H, W)) that `tonemap.hdr_encode_rgb` encodes, before
    10-bit quantisation: channels times `white_balance`, BT.709 -> `primaries` (`tonemap.primaries_matrix`),
    each channel's light as in `display_reference` (hlg: the grey OOTF per channel, 1000 E^1.2); with
    `peak` > 0 the BT.2390 EETF maps max(R, G, B) and the channels are scaled alike (hlg: in scene light E).
    The reference for measuring a colour encode (`code_light` of the decoded R'G'B')."""
    from .tonemap import eetf_BT2390, hlg_reference_E, primaries_matrix
    _check_transfer(transfer)
    v = np.asarray(rgb, np.float32).astype(np.float64)      # the kernel's float32 input
    gains = np.asarray(white_balance, np.float64).reshape(-1)
    if v.ndim != 3 or v.shape[0] != 3 or gains.shape != (3,):
        raise ValueError(f"display_reference_rgb: need planar RGB (3, H, W) and three gains, got shape {v.shape} "
                         f"and {white_balance!r}")
    c = np.clip(np.nan_to_num(v * gains[:, None, None], nan=0.0, posinf=1e30), 0.0, 1e30)
    m = primaries_matrix("bt709", primaries) if primaries != "bt709" else np.eye(3)
    t = np.tensordot(m, c, axes=1)
    gain = 2.0 ** exposure_stops / diffuse_white
    if transfer == "pq":
        L = np.minimum(t * (gain * reference_white), L_P)
        if peak > 0:
            top = L.max(axis=0)
            k = np.divide(eetf_BT2390(top, min(source_peak, L_P), peak), top, out=np.zeros_like(top),
                          where=top > 0)
            L = L * k
        return L
    E = np.minimum(t * (gain * hlg_reference_E(reference_white)), 1e30)
    if peak > 0:
        top = E.max(axis=0)
        lm = np.minimum(HLG_NOMINAL_PEAK * top ** HLG_SYSTEM_GAMMA, L_P)
        em = np.minimum((eetf_BT2390(lm, min(source_peak, L_P), peak) / HLG_NOMINAL_PEAK)
                        ** (1.0 / HLG_SYSTEM_GAMMA), 1.0)
        E = E * np.divide(em, top, out=np.zeros_like(top), where=top > 0)
    return HLG_NOMINAL_PEAK * np.minimum(E, 1.0) ** HLG_SYSTEM_GAMMA


def _upsample(c: np.ndarray, n: int, axis: int, offset: float) -> np.ndarray:
    """Linear interpolation of the chroma samples along `axis` (sample i at luma position 2 i + offset) at
    the n luma positions; the edge samples extend outwards."""
    pos = np.clip((np.arange(n) - offset) / 2.0, 0.0, c.shape[axis] - 1)
    i0 = np.floor(pos).astype(np.intp)
    i1 = np.minimum(i0 + 1, c.shape[axis] - 1)
    f = pos - i0
    shape = [1] * c.ndim
    shape[axis] = n
    f = f.reshape(shape)
    return np.take(c, i0, axis=axis) * (1.0 - f) + np.take(c, i1, axis=axis) * f


def rgb_from_ycbcr420(y: np.ndarray, cb: np.ndarray, cr: np.ndarray, matrix: str = "bt2020") -> np.ndarray:
    """What a player shows of 10-bit narrow-range Y' (H, W) and 4:2:0 Cb, Cr (ceil(H/2), ceil(W/2)) codes: the
    chroma interpolated linearly to every pixel at HEVC's default siting (type 0, as `ycbcr_frame` writes it:
    horizontally co-sited, vertically between the two rows), then the inverse of `matrix`'s Y'CbCr
    (R' = Y' + (2 - 2 Kr) Cr, B' = Y' + (2 - 2 Kb) Cb, G' from Y'): R'G'B' code values (3, H, W), float64."""
    if matrix not in MATRICES:
        raise ValueError(f"Y'CbCr matrix must be one of {', '.join(MATRICES)}, got {matrix!r}")
    y = np.asarray(y, np.float64)
    h, w = y.shape
    if np.shape(cb) != ((h + 1) // 2, (w + 1) // 2) or np.shape(cr) != np.shape(cb):
        raise ValueError(f"4:2:0 chroma of a {w}x{h} picture must be {(w + 1) // 2}x{(h + 1) // 2}, got Cb "
                         f"{np.shape(cb)}, Cr {np.shape(cr)}")
    kr, kb = MATRICES[matrix]
    yy = (y - 64.0) / 876.0
    chroma = []
    for c in (cb, cr):
        c = (np.asarray(c, np.float64) - 512.0) / 896.0
        chroma.append(_upsample(_upsample(c, h, 0, 0.5), w, 1, 0.0))
    r = yy + (2.0 - 2.0 * kr) * chroma[1]
    b = yy + (2.0 - 2.0 * kb) * chroma[0]
    g = (yy - kr * r - kb * b) / (1.0 - kr - kb)
    return 64.0 + 876.0 * np.stack([r, g, b])


def ycbcr420_planes(codes: np.ndarray, shift: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Y', Cb, Cr) code planes of the 4:2:0 frame `ycbcr_frame` makes of R'G'B' codes (3, H, W) (<< shift):
    what the encoder is given."""
    h, w = np.shape(codes)[1:]
    cw, ch = (w + 1) // 2, (h + 1) // 2
    frame = np.zeros(2 * (h * w + 2 * ch * cw), np.uint8)
    ycbcr_frame(np.asarray(codes, np.uint16), frame, (0, 2 * h * w, 2 * (h * w + ch * cw)), (2 * w, 2 * cw, 2 * cw),
                shift=shift)
    words = frame.view("<u2")
    return (words[:h * w].reshape(h, w), words[h * w:h * w + ch * cw].reshape(ch, cw),
            words[h * w + ch * cw:].reshape(ch, cw))


def luminance_light(light: np.ndarray) -> np.ndarray:
    """BT.2020 luminance (cd/m^2) of BT.2020 display light per channel, channels first: 0.2627 R + 0.6780 G +
    0.0593 B (ITU-R BT.2020 Table 4)."""
    kr, kb = LUMA_BT2020
    return kr * light[0] + (1.0 - kr - kb) * light[1] + kb * light[2]


def light_scores(reference, test, transfer: str = "pq") -> dict:
    """`test` display light (cd/m^2) against `reference` (same shape, any number of frames): PU21-PSNR
    (`metrics.pu21_psnr` of the light as luminance) and log2 PSNR (`metrics.log2_psnr`, 0.1 cd/m^2 floor) in
    dB, and the error of its 10-bit code values against the reference's exact codes (`light_code`): mean,
    mean absolute, largest absolute."""
    from . import metrics
    ref = np.asarray(reference, np.float64)
    tst = np.asarray(test, np.float64)
    if ref.shape != tst.shape:
        raise ValueError(f"the test light has shape {tst.shape}, the reference {ref.shape}")
    err = light_code(tst, transfer) - light_code(ref, transfer)
    return {"pu21_psnr": float(metrics.pu21_psnr(ref, tst, white=1.0, peak_nits=1.0)),
            "log2_psnr": float(metrics.log2_psnr(ref, tst, floor=0.1)),
            "code_error_mean": float(err.mean()), "code_error_abs_mean": float(np.abs(err).mean()),
            "code_error_abs_max": float(np.abs(err).max())}


def ciede2000_scores(reference, test, reference_white: float = REFERENCE_WHITE_NITS) -> dict:
    """CIEDE2000 (`metrics.ciede2000`) of BT.2020 display light `test` against `reference` (cd/m^2, channels
    on axis -3: (3, H, W) or (N, 3, H, W)). CIELAB's white is D65 at `reference_white` cd/m^2 (the diffuse
    white, BT.2408); only pixels whose reference luminance is at most that white are scored (CIELAB's range,
    L* <= 100; the highlights above it are scored per channel). Returns the mean, the 95th percentile and
    the share of the pixels scored (None where no pixel is)."""
    from . import metrics
    from .tonemap import rgb_to_xyz_matrix
    ref = np.moveaxis(np.asarray(reference, np.float64), -3, 0)
    tst = np.moveaxis(np.asarray(test, np.float64), -3, 0)
    if ref.shape != tst.shape or ref.shape[0] != 3:
        raise ValueError(f"CIEDE2000 needs two colour pictures of one shape (3 channels), got {ref.shape} and "
                         f"{tst.shape}")
    m = rgb_to_xyz_matrix("bt2020")
    white = m.sum(axis=1) * float(reference_white)
    inside = luminance_light(ref) <= reference_white * (1.0 + 1e-9)      # (the white itself, not its rounding)
    if not inside.any():
        return {"mean": None, "p95": None, "share": 0.0}
    lab = [metrics.xyz_to_lab(np.tensordot(m, x[:, inside], axes=1), white) for x in (ref, tst)]
    de = metrics.ciede2000(lab[0], lab[1])
    return {"mean": float(de.mean()), "p95": float(np.percentile(de, 95)), "share": float(inside.mean())}


def quality_report(reference, test, transfer: str = "pq", reference_white: float = REFERENCE_WHITE_NITS) -> dict:
    """The `nrhdr hdr10 --report` figures of `test` display light against `reference` (cd/m^2): grey frames
    (N, H, W): {"Y": light_scores}; colour (N, 3, H, W) in BT.2020: per channel "R", "G", "B", the BT.2020
    luminance "Y" (`luminance_light`) and "ciede2000" (`ciede2000_scores`)."""
    ref = np.asarray(reference, np.float64)
    tst = np.asarray(test, np.float64)
    if ref.ndim != 4:
        return {"Y": light_scores(ref, tst, transfer)}
    rep = {name: light_scores(ref[:, i], tst[:, i], transfer) for i, name in enumerate("RGB")}
    rep["Y"] = light_scores(luminance_light(np.moveaxis(ref, 1, 0)), luminance_light(np.moveaxis(tst, 1, 0)),
                            transfer)
    rep["ciede2000"] = ciede2000_scores(ref, tst, reference_white)
    return rep


def encoder_caps(transfer: str, mastering: MasteringDisplay | None = None,
                 levels: tuple[int, int] | None = None) -> str:
    """The video caps (text) x265enc is given: I420_10LE, colorimetry bt2100-pq / bt2100-hlg (BT.2020, PQ or
    HLG, BT.2020 NCL, limited range in the VUI) and, with `mastering` and `levels` (MaxCLL, MaxFALL), the
    fields from which it writes the ST 2086 and CTA-861.3 SEI."""
    caps = f"video/x-raw,format=I420_10LE,colorimetry=bt2100-{transfer}"
    if mastering is not None and levels is not None:
        caps += (f",mastering-display-info=(string){mastering.caps_field()},"
                 f"content-light-level=(string){content_light_caps_field(*levels)}")
    return caps


def matroska_caps(mastering: MasteringDisplay) -> str:
    """The caps (text) that a capssetter before matroskamux sets so that its Colour element states the
    mastering luminance the SEI states (MATROSKA_LUMINANCE_FACTOR)."""
    return f"video/x-h265,mastering-display-info=(string){mastering.caps_field(MATROSKA_LUMINANCE_FACTOR)}"


def check_encode_size(width: int, height: int, where: str) -> None:
    """ValueError naming `where` for a frame narrower than MIN_ENCODE_WIDTH: x265enc (libx265, GStreamer's
    x265 plugin on Debian 12) corrupts its heap and aborts (`free(): invalid next size`) on such frames at some
    sizes (widths 34 to 48 at heights of 32 and more, measured with videotestsrc), so the HEVC route refuses
    them all before the first frame."""
    if int(width) < MIN_ENCODE_WIDTH:
        raise ValueError(f"{where}: {width}x{height} frames are narrower than {MIN_ENCODE_WIDTH} pixels (one HEVC "
                         f"coding tree unit), which x265enc cannot encode reliably: encode frames at least "
                         f"{MIN_ENCODE_WIDTH} pixels wide")


def warmup_rgb(transfers=TRANSFERS, elements: bool = False) -> None:
    """Compile (or load) the colour HDR kernels (`tonemap.hdr_encode_rgb`, with and without the roll-off, and
    `ycbcr_frame` 4:2:0 and 4:4:4, from writeable and read-only codes) on a tiny frame; `elements`: also a
    read-only input (nrtonemap's mapped buffers)."""
    from .tonemap import hdr_encode_rgb
    h, w = 4, 6
    v = np.geomspace(1.0, 1e4, 3 * h * w).astype(np.float32).reshape(3, h, w)
    inputs = [v]
    if elements:
        ro = v.copy()
        ro.setflags(write=False)
        inputs.append(ro)
    for x in inputs:
        for transfer in transfers:
            for peak in (0.0, DEFAULT_PEAK):
                codes = hdr_encode_rgb(x, 1e3, transfer, peak=peak, source_peak=2 * peak)
    frame = np.zeros(3 * h * w * 2, np.uint8)
    ro_codes = codes.copy()
    ro_codes.setflags(write=False)          # `nrhdr hdr10` reads its codes from a read-only memory map
    for sub in (True, False):
        for c in (codes, ro_codes):
            ycbcr_frame(c, frame, (0, h * w * 2, 2 * h * w * 2), (w * 2, w * 2, w * 2), subsample=sub)
