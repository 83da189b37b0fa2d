#!/usr/bin/env bash
# Raw clip -> HDR video for HDR televisions and players (docs/HDR-OUTPUT.md): HEVC Main 10 through x265enc,
# BT.2020 / PQ (HDR10) or HLG / BT.2020 non-constant luminance / limited range, with the SMPTE ST 2086
# mastering display and the CTA-861.3 MaxCLL / MaxFALL measured over the clip's frames (PQ).
#   pipelines/raw_to_hdr10.sh [CLIP_DIR [OUT [PROFILE]]]
# OUT.mp4 or OUT.mkv: that file (the container by the suffix); any other OUT: OUT.mkv. FORMAT=png (or no x265enc
# installed): 16-bit PNG stills OUT/frame_%05d.png with a cICP chunk. Defaults: CLIP_DIR=demo_out/clip,
# OUT=CLIP_DIR_hdr10. Two passes (`nrhdr hdr10`): the chain and the light levels, then the encode.
# Environment: TRANSFER (pq|hlg, default pq), REFERENCE_WHITE (cd/m2 of the diffuse white, default 203), PEAK
# (mastering peak in cd/m2, default 1000: brighter light is rolled off by the BT.2390 EETF), EXPOSURE, CRF,
# SPEED_PRESET, FORMAT (auto|mp4|mkv|png), METHOD, PRESET, MODE, CROSSTALK, NRHDR, OVERWRITE (true: replace OUT).
# The video is written as OUT.part and renamed when complete; a stop (Ctrl-C) while encoding ends it with EOS
# (the file is closed and plays the frames encoded so far), a stop during the first pass leaves no file.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,14p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
nr_clip "$CLIP" "${3:-}"
OUT="${2:-${CLIP%/}_hdr10}"
FORMAT="${FORMAT:-auto}"
case "$FORMAT" in auto|mp4|mkv|png) ;; *) echo "error: FORMAT=$FORMAT: use auto, mp4, mkv or png" >&2; exit 2;; esac
if [ "$FORMAT" != png ] && ! gst-inspect-1.0 --exists x265enc; then
  if [ "$FORMAT" != auto ]; then
    echo "error: x265enc is not installed (Debian: gstreamer1.0-plugins-bad)" >&2; exit 2
  fi
  echo "raw_to_hdr10.sh: x265enc is not installed (gstreamer1.0-plugins-bad): writing 16-bit PNG stills" >&2
  FORMAT=png
fi
if [ "$FORMAT" = png ]; then
  TARGET="$OUT"
else
  case "$OUT" in
    *.mp4|*.mkv) TARGET="$OUT"; [ "$FORMAT" = auto ] || [ "${OUT##*.}" = "$FORMAT" ] \
      || { echo "error: FORMAT=$FORMAT but OUT is $OUT" >&2; exit 2; } ;;
    *) TARGET="$OUT.${FORMAT/auto/mkv}" ;;
  esac
fi
if [ "${OVERWRITE:-false}" != "true" ] && [ -e "$TARGET" ] \
    && { [ ! -d "$TARGET" ] || [ -n "$(ls -A "$TARGET")" ]; }; then
  echo "error: $TARGET exists: choose another name or set OVERWRITE=true" >&2; exit 2
fi
ARGS=(--profile "$PROFILE" --transfer "${TRANSFER:-pq}" --reference-white "${REFERENCE_WHITE:-203}"
      --peak "${PEAK:-1000}" --exposure "${EXPOSURE:-0}" --method "${METHOD:-fse}" --preset "${PRESET:-fast}"
      --mode "${MODE:-threshold}" --crosstalk "${CROSSTALK:-kernel}" --fps "$FPS")
[ -z "${CRF:-}" ] || ARGS+=(--crf "$CRF")
[ -z "${SPEED_PRESET:-}" ] || ARGS+=(--speed-preset "$SPEED_PRESET")
[ "${OVERWRITE:-false}" != "true" ] || ARGS+=(--force)
[ -t 2 ] || ARGS+=(--no-progress)
exec "$NRHDR" hdr10 "$CLIP" "$TARGET" "${ARGS[@]}"
