#!/usr/bin/env bash
# Raw clip -> live preview on the screen (autovideosink), played at the clip's frame rate.
#   pipelines/raw_to_display.sh [CLIP_DIR [PROFILE]]
# Defaults: CLIP_DIR=demo_out/clip, PROFILE=CLIP_DIR/camera.json.
# Environment: CROSSTALK (nrcrosstalk mode, default lut), METHOD (default preview: fast enough for live video), PRESET, MODE, EXPOSURE, OPERATOR (local|log), NRHDR,
# SINK (a sink and its properties, replacing the choice below).
# Without a display (no DISPLAY, no Wayland display with XDG_RUNTIME_DIR) the frames go to fakesink, said on
# stderr; on X11 without a Wayland display an X sink is named (autovideosink would try waylandsink first, which
# crashes when XDG_RUNTIME_DIR is unset). pipelines/raw_to_display_headless.sh measures the frame rate headless.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,10p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
CROSSTALK="${CROSSTALK:-lut}"   # live: the per-pixel LUT (the kernel takes ~10x longer)
nr_clip "$CLIP" "${2:-}"
nr_display_sink
exec "$NRHDR" launch "${SRC[@]}" \
  ! nrreconstruct "method=${METHOD:-preview}" "preset=${PRESET:-preview}" \
  ! queue max-size-buffers=2 ! nrtonemap "exposure=${EXPOSURE:-0}" "operator=${OPERATOR:-local}" \
  ! videoconvert ! "${SINKV[@]}"
