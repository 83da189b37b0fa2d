#!/usr/bin/env bash
# Raw clip -> linear HDR OpenEXR sequence (float32 Y + state channel): OUT_DIR/frame_%05d.exr.
#   pipelines/raw_to_exr.sh [CLIP_DIR [OUT_DIR [PROFILE]]]
# Defaults: CLIP_DIR=demo_out/clip, OUT_DIR=CLIP_DIR_exr, PROFILE=CLIP_DIR/camera.json.
# Environment: METHOD (default fse), PRESET (default fast), MODE, NRHDR, OVERWRITE (true: replace an
# existing frame_*.exr sequence in OUT_DIR; default: refuse).
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,6p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
nr_clip "$CLIP" "${3:-}"
OUT="${2:-${CLIP%/}_exr}"
nr_out "$OUT" exr
nr_launch "${SRC[@]}" \
  ! nrreconstruct "method=${METHOD:-fse}" "preset=${PRESET:-fast}" \
  ! nrexrsink "location=$OUT/frame_%05d.exr" write-state=true
