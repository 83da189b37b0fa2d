# Sourced by the pipelines/*.sh scripts: finds the `nrhdr` command and reads a clip folder's clip.json.
# Clip folders come from `nrhdr simulate -o DIR` (or `make demo`: demo_out/clip): clip.raw (GRAY16_LE),
# clip.json {width, height, fps, frames, raw, profile}, camera.json (+ camera_mask.png).
set -euo pipefail

NR_PIPELINES="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
NR_ROOT="$(dirname "$NR_PIPELINES")"

# NRHDR: the nrhdr command (env override), else this checkout's .venv, else PATH.
if [ -z "${NRHDR:-}" ]; then
  if [ -x "$NR_ROOT/.venv/bin/nrhdr" ]; then
    NRHDR="$NR_ROOT/.venv/bin/nrhdr"
  elif command -v nrhdr >/dev/null 2>&1; then
    NRHDR="$(command -v nrhdr)"
  else
    echo "error: the nrhdr command was not found: run 'make setup' (or set NRHDR=/path/to/nrhdr)" >&2
    exit 2
  fi
fi

# nr_clip CLIP_DIR [PROFILE]: sets RAW, PROFILE, W, H, FPS, FRAMES and SRC (filesrc ! rawvideoparse !
# nrvalidity ...) from CLIP_DIR/clip.json; PROFILE defaults to the clip's camera.json.
nr_clip() {
  local dir="$1" prof="${2:-}"
  if [ ! -f "$dir/clip.json" ]; then
    echo "error: $dir is not a clip folder (no clip.json); make one with: nrhdr simulate -o $dir" >&2
    exit 2
  fi
  local vals
  vals="$(python3 - "$dir/clip.json" <<'PY'
import json, sys
try:
    c = json.load(open(sys.argv[1]))
    print(int(c["width"]), int(c["height"]), int(c["fps"]), int(c.get("frames", 0)),
          c.get("raw", "clip.raw"), c.get("profile", "camera.json"), sep="\n")
except (OSError, ValueError, KeyError, TypeError) as e:
    sys.exit(f"error: {sys.argv[1]}: cannot read the clip description: {e}")
PY
)"
  { read -r W; read -r H; read -r FPS; read -r FRAMES; read -r raw_name; read -r prof_name; } <<<"$vals"
  RAW="$dir/$raw_name"
  PROFILE="${prof:-$dir/$prof_name}"
  if [ ! -f "$RAW" ]; then echo "error: raw video $RAW not found" >&2; exit 2; fi
  # plane-strides: rows are stored without padding (also for odd widths, where GStreamer's default
  # GRAY16_LE stride would be rounded up to 4 bytes).
  SRC=(filesrc "location=$RAW" ! rawvideoparse format=gray16-le "width=$W" "height=$H"
       "framerate=$FPS/1" "plane-strides=<$((2 * W))>" ! nrvalidity "profile=$PROFILE"
       "mode=${MODE:-threshold}" ! nrcrosstalk)
}

# nr_out DIR EXT: make the output folder of a frame sequence (frame_%05d.EXT). An existing sequence there is
# refused (old and new frames would mix) unless OVERWRITE=true, which deletes only its frame_NNNNN.EXT files.
nr_out() {
  local dir="$1" ext="$2" old
  mkdir -p "$dir"
  old="$(find "$dir" -maxdepth 1 -regextype posix-extended -regex ".*/frame_[0-9]+\.$ext" | head -n 1)"
  if [ -n "$old" ]; then
    if [ "${OVERWRITE:-false}" != "true" ]; then
      echo "error: $dir already holds a recording ($old ...): choose another folder or set OVERWRITE=true" >&2
      exit 2
    fi
    find "$dir" -maxdepth 1 -regextype posix-extended -regex ".*/frame_[0-9]+\.$ext" -delete
  fi
}

# nr_launch ARGS...: run `"$NRHDR" launch ARGS` for a script that must do something after the pipeline (else
# use `exec "$NRHDR" launch ...`: the signal then reaches nrhdr directly). SIGINT, SIGTERM and SIGHUP to the
# script are forwarded to nrhdr, which stops the pipeline with EOS (docs/ELEMENTS.md, "Stopping"); returns
# nrhdr's status (130/143/129 after a signal), so with `set -e` the script stops there.
nr_launch() {
  local pid rc=0
  "$NRHDR" launch "$@" &
  pid=$!
  trap 'kill -INT "$pid" 2>/dev/null || true' INT
  trap 'kill -TERM "$pid" 2>/dev/null || true' TERM
  trap 'kill -HUP "$pid" 2>/dev/null || true' HUP
  while :; do
    wait "$pid" && rc=0 || rc=$?
    kill -0 "$pid" 2>/dev/null || break   # wait was interrupted by a forwarded signal: wait again
  done
  trap - INT TERM HUP
  return "$rc"
}
