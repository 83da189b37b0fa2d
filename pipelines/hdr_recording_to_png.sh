#!/usr/bin/env bash
# Play back a raw HDR recording (pipelines/raw_to_hdr_recording.sh) with plain filesrc ! capsfilter:
# tone-mapped 8-bit PNG frames OUT_DIR/frame_%05d.png.
#   pipelines/hdr_recording_to_png.sh REC [OUT_DIR]
# REC.caps holds the caps; filesrc's blocksize must be one frame (5*W*H bytes), else nrtonemap refuses the
# buffers. An existing PNG sequence in OUT_DIR is refused unless OVERWRITE=true. Environment: EXPOSURE
# (stops), OPERATOR (local|log, default local), NRHDR, OVERWRITE.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help|"") sed -n '2,6p' "$0"; exit 0;; esac
REC="$1"
OUT="${2:-${REC%.nrhdr}_png}"
if [ ! -f "$REC" ] || [ ! -f "$REC.caps" ]; then
  echo "error: $REC or $REC.caps not found (record with pipelines/raw_to_hdr_recording.sh)" >&2; exit 2
fi
CAPS="$(cat "$REC.caps")"
W="$(sed -n 's/.*width=(int)\([0-9]*\).*/\1/p' <<<"$CAPS")"
H="$(sed -n 's/.*height=(int)\([0-9]*\).*/\1/p' <<<"$CAPS")"
nr_out "$OUT" png
nr_launch filesrc "location=$REC" "blocksize=$((5 * W * H))" ! "$CAPS" \
  ! nrtonemap "exposure=${EXPOSURE:-0}" "operator=${OPERATOR:-local}" ! video/x-raw,format=GRAY8 \
  ! pngenc ! multifilesink "location=$OUT/frame_%05d.png"
