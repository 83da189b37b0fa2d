#!/usr/bin/env bash
# Raw still sequence (16-bit gray TIFF / PNG, one frame per file, any camera) -> linear HDR OpenEXR sequence
# (float32 Y + state channel): OUT_DIR/frame_%05d.exr; equal to `nrhdr batch STILLS --profile PROFILE`.
#   pipelines/stills_to_hdr.sh STILLS [OUT_DIR [PROFILE]]
# STILLS: a folder of .tif/.tiff/.png files of one kind (natural order), or a pattern: dir/frame_%05d.tif.
# Defaults: OUT_DIR=<the stills' folder>_exr, PROFILE=$PROFILE, else the stills' folder's camera.json.
# Environment: FPS (frame rate N/D, default 30/1), START (pattern: first index, default the lowest),
# METHOD (default fse), PRESET (default fast), MODE, CROSSTALK, NRHDR, OVERWRITE (true: replace an existing
# frame_*.exr sequence in OUT_DIR; default: refuse).
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in
  -h|--help) sed -n '2,9p' "$0"; exit 0;;
  "") echo "error: no still sequence given" >&2; sed -n '4,6p' "$0" >&2; exit 2;;
esac
STILLS="$1"
if [ -d "$STILLS" ]; then DIR="${STILLS%/}"; else DIR="$(dirname "$STILLS")"; fi
PROFILE="${3:-${PROFILE:-$DIR/camera.json}}"
if [ ! -f "$PROFILE" ]; then
  echo "error: camera profile $PROFILE not found: give it as the third argument or in PROFILE" >&2
  exit 2
fi
OUT="${2:-${DIR}_exr}"
nr_out "$OUT" exr
nr_launch nrimagesrc "location=$STILLS" "framerate=${FPS:-30/1}" "start-index=${START:--1}" \
  ! nrvalidity "profile=$PROFILE" "mode=${MODE:-threshold}" ! nrcrosstalk "mode=${CROSSTALK:-kernel}" \
  ! nrreconstruct "method=${METHOD:-fse}" "preset=${PRESET:-fast}" \
  ! nrexrsink "location=$OUT/frame_%05d.exr" write-state=true
