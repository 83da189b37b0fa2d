#!/usr/bin/env bash
# Live camera -> lossless raw recording + live HDR preview that may drop frames (issue #7).
#   pipelines/live_record_and_preview.sh [CLIP_DIR [OUT_DIR]]
# nrcamsrc plays CLIP_DIR (a clip folder of `nrhdr simulate`, default demo_out/clip) live at its frame rate;
# a tee right after the camera feeds (1) a recording branch, a plain blocking queue into a raw GRAY16_LE file
# (OUT_DIR/clip.raw + clip.json naming the camera profile: a clip folder again, reprocessable offline at any quality),
# and (2) a display branch behind `queue leaky=downstream max-size-buffers=2` through the chain with
# method=auto into a sync=true sink. When the display is late it drops frames (leaky queue, QoS); the
# recording never does. Environment: FRAMES (num-buffers, default 150), LOOP (true/false), METHOD (auto),
# PRESET, FPS (0 = the clip's), SINK (default autovideosink with a display, else a QoS fakesink), VERBOSE=1
# (gst-launch -m: bus messages), STATS=true (nrreconstruct posts nrhdr-frame-stats), FORCE=1 (replace OUT_DIR/clip.raw), NRHDR.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,12p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
NBUF="${FRAMES:-150}" RATE="${FPS:-0}"   # read before nr_clip, which sets FRAMES and FPS from the clip
nr_clip "$CLIP"
OUT="${2:-${CLIP%/}_live}"
if [ -e "$OUT/clip.raw" ] && [ "${FORCE:-0}" != 1 ]; then
  echo "error: $OUT/clip.raw exists (FORCE=1 replaces it)" >&2; exit 2
fi
mkdir -p "$OUT"
PART="$OUT/.clip.raw.part"
if [ -n "${SINK:-}" ]; then
  read -r -a SINKV <<<"$SINK"
elif [ -n "${DISPLAY:-}${WAYLAND_DISPLAY:-}" ]; then
  SINKV=(autovideosink sync=true)
else  # a video sink's defaults: sync, QoS events upstream, frames more than 20 ms late dropped
  SINKV=(fakesink sync=true qos=true max-lateness=20000000)
fi
ARGS=()
[ "${VERBOSE:-0}" = 1 ] && ARGS+=(-m)
rm -f "$PART"
nr_launch "${ARGS[@]}" nrcamsrc "location=$CLIP" "num-buffers=$NBUF" "loop=${LOOP:-true}" \
    "fps=$RATE" ! tee name=t \
  t. ! queue max-size-buffers=0 max-size-bytes=0 max-size-time=10000000000 ! filesink "location=$PART" \
  t. ! queue leaky=downstream max-size-buffers=2 ! nrvalidity "profile=$PROFILE" "mode=${MODE:-threshold}" \
    ! nrcrosstalk ! nrreconstruct "method=${METHOD:-auto}" "preset=${PRESET:-fast}" "post-stats=${STATS:-false}" ! nrtonemap \
    ! videoconvert ! "${SINKV[@]}" || { rc=$?; rm -f "$PART"; exit "$rc"; }
# the recording is a clip folder: raw frames, the camera's profile, clip.json (written last, atomically)
python3 - "$CLIP/clip.json" "$PART" "$OUT" "$PROFILE" <<'PY'
import json, os, sys
src, part, out, prof = sys.argv[1:]
c = json.load(open(src))
fb = 2 * int(c["width"]) * int(c["height"])
size = os.path.getsize(part)
if size % fb:
    sys.exit(f"error: {part}: {size} bytes is not a whole number of frames")
os.replace(part, os.path.join(out, "clip.raw"))
# the camera's profile stays where it is (its mask and calibration files beside it): absolute path
c.update(frames=size // fb, raw="clip.raw", profile=os.path.abspath(prof), truth=None,
         recorded_from=os.path.abspath(src))
tmp = os.path.join(out, ".clip.json.part")
open(tmp, "w").write(json.dumps(c, indent=2) + "\n")
os.replace(tmp, os.path.join(out, "clip.json"))
print(f"recorded {size // fb} frames to {out}/clip.raw (clip folder)")
PY
