"""HDR10 / HLG delivery metadata (docs/HDR-OUTPUT.md): the SMPTE ST 2086 mastering display and the CTA-861.3
content light levels (MaxCLL, MaxFALL) measured from the 10-bit codes a clip is encoded with, their text forms
(the `mastering-display-info` / `content-light-level` caps fields of GStreamer video caps and x265's options),
and the encoder settings chosen by measurement (docs/BENCHMARKS.md, "HDR10 encoding").

Codes are BT.2100 10-bit narrow range (64..940), as `tonemap.hdr_encode` writes them (<< 6 in uint16).
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
from numba import njit, prange

from .tonemap import (HLG_NOMINAL_PEAK, HLG_SYSTEM_GAMMA, L_P, LUMA_BT709, LUMA_BT2020, REFERENCE_WHITE_NITS,
                      RGB_PRIMARIES, TRANSFERS, WHITE_D65, eotf_ST2084, oetf_inverse_HLG, peak_luminance)

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
    if transfer not in TRANSFERS:
        raise ValueError(f"HDR transfer must be one of {', '.join(TRANSFERS)}, got {transfer!r}")
    sig = np.clip((np.arange(1024) - 64.0) / 876.0, 0.0, 1.0)
    if transfer == "pq":
        return eotf_ST2084(sig)
    return HLG_NOMINAL_PEAK * oetf_inverse_HLG(sig) ** HLG_SYSTEM_GAMMA


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


def warmup_rgb(transfers=TRANSFERS, elements: bool = False) -> None:
    """Compile (or load) the colour HDR kernels (`tonemap.hdr_encode_rgb`, with and without the roll-off, and
    `ycbcr_frame` 4:2:0 and 4:4:4) on a tiny frame; `elements`: also a read-only input (nrtonemap's mapped
    buffers)."""
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
    for sub in (True, False):
        ycbcr_frame(codes, frame, (0, h * w * 2, 2 * h * w * 2), (w * 2, w * 2, w * 2), subsample=sub)
