#!/usr/bin/env bash
# Raw clip -> 10-bit HDR video for HDR displays (BT.2100 PQ or HLG, narrow range, colorimetry in the caps).
#   pipelines/raw_to_hdr10.sh [CLIP_DIR [OUT [PROFILE]]]
# With a 10-bit encoder (vp9enc of gst-plugins-good, built with high bit depth; or x265enc): OUT.mkv, VP9
# profile 2 / HEVC Main10 in Matroska. Without one, or with FORMAT=png: 16-bit PNG frames OUT/frame_%05d.png
# (the 10-bit code << 6, gray). Defaults: CLIP_DIR=demo_out/clip, OUT=CLIP_DIR_hdr10.
# Environment: TRANSFER (pq|hlg, default pq), REFERENCE_WHITE (cd/m2 of the diffuse white, default 203),
# FORMAT (auto|mkv|png), METHOD, PRESET, MODE, EXPOSURE, NRHDR, OVERWRITE (true: replace an existing OUT.mkv
# or PNG sequence; default: refuse). The video is written as OUT.mkv.part and renamed when the pipeline ends;
# a stop (Ctrl-C, SIGTERM) ends it with EOS, so the file is closed and plays.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,11p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
nr_clip "$CLIP" "${3:-}"
OUT="${2:-${CLIP%/}_hdr10}"
TRANSFER="${TRANSFER:-pq}"
FORMAT="${FORMAT:-auto}"
ENC=()
if [ "$FORMAT" != png ]; then
  if gst-inspect-1.0 --exists x265enc; then
    ENC=(x265enc ! h265parse)
  elif gst-inspect-1.0 --exists vp9enc; then
    ENC=(vp9enc deadline=1 lag-in-frames=0)
  elif [ "$FORMAT" = mkv ]; then
    echo "error: no 10-bit encoder (x265enc, vp9enc) installed" >&2; exit 2
  fi
fi
HDR=(nrreconstruct "method=${METHOD:-fse}" "preset=${PRESET:-fast}"
     ! nrtonemap "transfer=$TRANSFER" "reference-white=${REFERENCE_WHITE:-203}" "exposure=${EXPOSURE:-0}")
if [ ${#ENC[@]} -gt 0 ]; then
  nr_lock "$OUT.mkv"
  nr_refuse "$OUT.mkv"
  rc=0
  nr_launch "${SRC[@]}" ! "${HDR[@]}" \
    ! videoconvert ! "video/x-raw,format=I420_10LE,colorimetry=bt2100-$TRANSFER" \
    ! "${ENC[@]}" ! matroskamux ! filesink "location=$OUT.mkv.part" || rc=$?
  # EOS (also after a stop signal) closed the container: keep what was encoded
  if [ -s "$OUT.mkv.part" ]; then mv -f "$OUT.mkv.part" "$OUT.mkv"; else rm -f "$OUT.mkv.part"; fi
  exit "$rc"
fi
nr_out "$OUT" png
nr_launch "${SRC[@]}" ! "${HDR[@]}" ! video/x-raw,format=GRAY16_BE \
  ! pngenc ! multifilesink "location=$OUT/frame_%05d.png"
