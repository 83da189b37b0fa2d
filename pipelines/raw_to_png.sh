#!/usr/bin/env bash
# Raw clip -> tone-mapped 8-bit PNG frames: OUT_DIR/frame_%05d.png.
#   pipelines/raw_to_png.sh [CLIP_DIR [OUT_DIR [PROFILE]]]
# Defaults: CLIP_DIR=demo_out/clip (make demo), OUT_DIR=CLIP_DIR_png, PROFILE=CLIP_DIR/camera.json.
# Environment: METHOD (fse|linear|nearest|preview, default fse), PRESET (preview|fast|balanced|best,
# default fast), MODE (threshold|all|best), EXPOSURE (stops, default 0), OPERATOR (nrtonemap operator: local
# or log, default local), NRHDR (the nrhdr command).
# OVERWRITE=true replaces an existing frame_*.png sequence in OUT_DIR (default: refuse).
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,8p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
nr_clip "$CLIP" "${3:-}"
OUT="${2:-${CLIP%/}_png}"
nr_out "$OUT" png
nr_launch "${SRC[@]}" \
  ! nrreconstruct "method=${METHOD:-fse}" "preset=${PRESET:-fast}" \
  ! nrtonemap "exposure=${EXPOSURE:-0}" "operator=${OPERATOR:-local}" ! video/x-raw,format=GRAY8 \
  ! pngenc ! multifilesink "location=$OUT/frame_%05d.png"
