#!/usr/bin/env bash
# Colour raw clip (nrhdr simulate --cfa) -> linear camera-RGB OpenEXR sequence (float32 R, G, B + state):
# OUT_DIR/frame_%05d.exr.
#   pipelines/colour_to_exr.sh [CLIP_DIR [OUT_DIR [PROFILE]]]
# Defaults: CLIP_DIR=demo_out/clip, OUT_DIR=CLIP_DIR_exr, PROFILE=CLIP_DIR/camera.json (its cfa: the Bayer phase).
# Environment: METHOD (preview, fse or auto; default fse), PRESET (default fast), MODE, CROSSTALK, NRHDR,
# OVERWRITE (true: replace an existing frame_*.exr sequence), DRY_RUN (1: print the pipeline, run nothing).
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,7p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
nr_clip "$CLIP" "${3:-}"
OUT="${2:-${CLIP%/}_exr}"
CFA="$(nr_py - "$PROFILE" <<'PY'
import json, sys
try:
    print(json.load(open(sys.argv[1])).get("cfa", "none"))
except (OSError, ValueError, AttributeError) as e:
    sys.exit(f"error: {sys.argv[1]}: cannot read the camera profile: {e}")
PY
)"
if [ "$CFA" = "none" ]; then
  echo "error: $PROFILE is a monochrome camera (cfa none): use pipelines/raw_to_exr.sh" >&2
  exit 2
fi
case "${METHOD:-fse}" in
  preview|fse|auto) ;;
  *) echo "error: METHOD=${METHOD}: a colour clip (cfa $CFA) takes preview, fse or auto" >&2; exit 2;;
esac
PIPE=("${SRC[@]}" \
  ! nrreconstruct "method=${METHOD:-fse}" "preset=${PRESET:-fast}" \
  ! "other/x-nrhdr,layout=rgb-f32-u8-planar" \
  ! nrexrsink "location=$OUT/frame_%05d.exr" write-state=true)
if [ "${DRY_RUN:-}" = "1" ]; then
  echo "${PIPE[*]}"
  exit 0
fi
nr_out "$OUT" exr
nr_launch "${PIPE[@]}"
