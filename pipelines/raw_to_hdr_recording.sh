#!/usr/bin/env bash
# Raw clip -> reconstructed linear HDR recording: the other/x-nrhdr frames as they travel between the
# elements (f32-u8-planar: 4*W*H bytes float32 values, then W*H state bytes, per frame, back to back),
# written by a plain filesink, plus REC.caps (the caps to read it back; pipelines/hdr_recording_to_png.sh).
#   pipelines/raw_to_hdr_recording.sh [CLIP_DIR [REC [PROFILE]]]
# Defaults: CLIP_DIR=demo_out/clip, REC=CLIP_DIR.nrhdr (refused if it exists unless OVERWRITE=true; written as
# REC.part and renamed when the pipeline ends: a stop by signal ends it with EOS and keeps every whole frame,
# a partial last frame is cut off). Environment: METHOD, PRESET, MODE, NRHDR, OVERWRITE.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,7p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
nr_clip "$CLIP" "${3:-}"
REC="${2:-${CLIP%/}.nrhdr}"
nr_lock "$REC"
nr_refuse "$REC"
# The caps nrvalidity will put on the stream (white, diffuse-white from the profile: docs/ELEMENTS.md).
nr_py - "$PROFILE" "$W" "$H" "$FPS" > "$REC.caps.tmp" <<'PY'
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
rc=0
nr_launch "${SRC[@]}" \
  ! nrreconstruct "method=${METHOD:-fse}" "preset=${PRESET:-fast}" \
  ! filesink "location=$REC.part" || rc=$?
# finished, stopped or failed: whole frames only, then the final names (the caps file last)
FB=$((5 * W * H))
SIZE="$(stat -c %s "$REC.part" 2>/dev/null || echo 0)"
if [ "$SIZE" -lt "$FB" ]; then
  rm -f "$REC.part" "$REC.caps.tmp"
  echo "no whole frame recorded; nothing written" >&2
  exit $(( rc ? rc : 1 ))
fi
truncate -s $(( SIZE / FB * FB )) "$REC.part"
mv -f "$REC.part" "$REC"
mv -f "$REC.caps.tmp" "$REC.caps"
echo "wrote $REC ($(( SIZE / FB )) frames of $FB bytes) and $REC.caps"
exit "$rc"
