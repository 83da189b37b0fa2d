#!/usr/bin/env bash
# Live-preview chain without a display: as raw_to_display.sh, but the frames end in fakesink (through
# fpsdisplaysink when gst-plugins-bad provides it, which then reports the frame rate with -v).
#   pipelines/raw_to_display_headless.sh [CLIP_DIR [PROFILE]]
# Environment: CROSSTALK (nrcrosstalk mode, default lut), METHOD (default preview), PRESET, MODE, EXPOSURE, OPERATOR (local|log), SYNC (true = play at the clip's frame
# rate, default; false = as fast as possible), NRHDR.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,7p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
CROSSTALK="${CROSSTALK:-lut}"   # live: the per-pixel LUT (the kernel takes ~10x longer)
nr_clip "$CLIP" "${2:-}"
SYNC="${SYNC:-true}"
if gst-inspect-1.0 --exists fpsdisplaysink 2>/dev/null; then
  SINK=(fpsdisplaysink text-overlay=false "sync=$SYNC" video-sink=fakesink)
else
  SINK=(fakesink "sync=$SYNC")
fi
exec "$NRHDR" launch "${SRC[@]}" \
  ! nrreconstruct "method=${METHOD:-preview}" "preset=${PRESET:-preview}" \
  ! queue max-size-buffers=2 ! nrtonemap "exposure=${EXPOSURE:-0}" "operator=${OPERATOR:-local}" \
  ! videoconvert ! "${SINK[@]}"
