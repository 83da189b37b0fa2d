#!/usr/bin/env bash
# Live camera -> lossless raw recording + live HDR preview that may drop frames.
#   pipelines/live_record_and_preview.sh [CLIP_DIR [OUT_DIR]]
# nrcamsrc plays CLIP_DIR (a clip folder of `nrhdr simulate`, default demo_out/clip) live at its frame rate;
# a tee right after the camera feeds (1) a recording branch, a plain blocking queue into a raw GRAY16_LE file
# (OUT_DIR/clip.raw + clip.json + a copy of the camera profile: a clip folder again, reprocessable offline at any
# quality), and (2) a display branch behind `queue leaky=downstream max-size-buffers=2` through the chain
# (nrcrosstalk mode=lut, nrreconstruct method=auto) into a sync=true sink. When the display is late it drops
# frames (leaky queue, QoS; a display that shows less than half of the frames is reported at the end); the
# recording never does. A stop (Ctrl-C, SIGTERM, SIGHUP, EOS, a pipeline error) keeps every whole frame
# recorded so far as a clip folder; after SIGKILL or power loss `nrhdr recover OUT_DIR` (or the next run of
# this script) finishes it. Environment: FRAMES (num-buffers, default 150), LOOP (true/false), METHOD (auto),
# PRESET, CROSSTALK (lut), FPS (0 = the clip's), SINK (default autovideosink with a display, else a QoS
# fakesink), VERBOSE=1 (gst-launch -m: bus messages), STATS=true (nrreconstruct posts nrhdr-frame-stats),
# FORCE=1 (replace OUT_DIR/clip.raw), NRHDR.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in -h|--help) sed -n '2,17p' "$0"; exit 0;; esac
CLIP="${1:-demo_out/clip}"
NBUF="${FRAMES:-150}" RATE="${FPS:-0}"   # read before nr_clip, which sets FRAMES and FPS from the clip
nr_clip "$CLIP"
OUT="${2:-${CLIP%/}_live}"
nr_lock "$OUT/clip.raw"
PART="$OUT/.clip.raw.part"
META="$OUT/.clip.json.part"
if [ -e "$PART" ]; then   # a recorder killed before it could finish: keep its frames
  nr_py -m gst_plugins.cli recover --lock-held "$OUT"
fi
if [ -e "$OUT/clip.raw" ] && [ "${FORCE:-0}" != 1 ]; then
  echo "error: $OUT/clip.raw exists (FORCE=1 replaces it)" >&2; exit 2
fi
nr_display_sink
ARGS=()
[ "${VERBOSE:-0}" = 1 ] && ARGS+=(-m)
# what a recovery needs to finish the raw file (frame size, profile), written before the first frame
nr_py - "$CLIP/clip.json" "$PROFILE" "$META" <<'PY'
import json, os, sys
from nrhdr_core import outputs
src, prof, meta = sys.argv[1:]
outputs.write_text(meta, json.dumps({"source_clip_json": os.path.abspath(src),
                                     "profile": os.path.abspath(prof)}) + "\n")
PY
: >"$PART"
rc=0
NRHDR_REPORT_DROPS=1 nr_launch "${ARGS[@]}" nrcamsrc "location=$CLIP" "num-buffers=$NBUF" "loop=${LOOP:-true}" \
    "fps=$RATE" ! tee name=t \
  t. ! queue max-size-buffers=0 max-size-bytes=0 max-size-time=10000000000 ! filesink "location=$PART" \
  t. ! queue leaky=downstream max-size-buffers=2 ! nrvalidity "profile=$PROFILE" "mode=${MODE:-threshold}" \
    ! nrcrosstalk "mode=${CROSSTALK:-lut}" ! nrreconstruct "method=${METHOD:-auto}" "preset=${PRESET:-fast}" \
    "post-stats=${STATS:-false}" ! nrtonemap ! videoconvert ! "${SINKV[@]}" || rc=$?
# stopped, finished or failed: the frames recorded so far become a clip folder (whole frames, clip.json last)
nr_py -m gst_plugins.cli recover --lock-held "$OUT"
exit "$rc"
