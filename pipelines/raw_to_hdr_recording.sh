#!/usr/bin/env bash
# Raw clip -> reconstructed linear HDR recording: the other/x-nrhdr frames as they travel between the
# elements (f32-u8-planar: 4*W*H bytes float32 values, then W*H state bytes, per frame, back to back),
# written by a plain filesink, plus REC.caps (the caps to read it back; pipelines/hdr_recording_to_png.sh).
#   pipelines/raw_to_hdr_recording.sh [CLIP_DIR [REC [PROFILE]]]
# Defaults: CLIP_DIR=demo_out/clip, REC=CLIP_DIR.nrhdr (refused if it exists unless OVERWRITE=true; written as
# REC.part and renamed at EOS). Environment: METHOD, PRESET, MODE, NRHDR, OVERWRITE.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,7p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
nr_clip "$CLIP" "${3:-}"
REC="${2:-${CLIP%/}.nrhdr}"
if [ -e "$REC" ] && [ "${OVERWRITE:-false}" != "true" ]; then
  echo "error: $REC exists: choose another name or set OVERWRITE=true" >&2; exit 2
fi
mkdir -p "$(dirname "$REC")"
# The caps nrvalidity will put on the stream (white, diffuse-white from the profile: docs/ELEMENTS.md).
python3 - "$PROFILE" "$W" "$H" "$FPS" > "$REC.caps.tmp" <<'PY'
import json, os, sys
p, w, h, fps = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
try:
    c = json.load(open(p))
    regular = float(c.get("clip_code", 4094)) - float(c.get("black_level", 0.0))
    white = regular * float(c["nd"])
except (OSError, ValueError, KeyError, TypeError) as e:
    sys.exit(f"error: {p}: cannot read the camera profile: {e}")
print(f"other/x-nrhdr,layout=(string)f32-u8-planar,width=(int){w},height=(int){h},framerate=(fraction){fps}/1,"
      f"white=(double){white!r},diffuse-white=(double){regular!r},profile=(string)\"{os.path.abspath(p)}\"")
PY
nr_launch "${SRC[@]}" \
  ! nrreconstruct "method=${METHOD:-fse}" "preset=${PRESET:-fast}" \
  ! filesink "location=$REC.part"
# complete or not at all: the recording gets its final name only after EOS (a stop by signal also ends in EOS)
mv "$REC.part" "$REC"
mv "$REC.caps.tmp" "$REC.caps"
echo "wrote $REC ($((5 * W * H)) bytes per frame) and $REC.caps"
