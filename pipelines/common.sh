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

# NR_PY: the Python beside the nrhdr command (its venv), else /usr/bin/python3; never a `python3` that only
# happens to be first on PATH (pyenv, conda: another version, or another install without our packages).
if [ -x "$(dirname "$NRHDR")/python3" ]; then
  NR_PY="$(dirname "$NRHDR")/python3"
elif [ -x /usr/bin/python3 ]; then
  NR_PY=/usr/bin/python3
else
  NR_PY=python3
fi
# nr_py ARGS...: NR_PY with this checkout's nrhdr_core importable
nr_py() { PYTHONPATH="$NR_ROOT${PYTHONPATH:+:$PYTHONPATH}" "$NR_PY" "$@"; }

# nr_lock TARGET: hold the write lock of TARGET (a file or folder) until the script exits: the lock file
# .NAME.lock beside it, flock(1), the same lock nrhdr's commands take (nrhdr_core/outputs.py); a second
# writer of TARGET is refused. The kernel releases it when the holder dies (also by SIGKILL).
nr_lock() {
  local target="$1" lp
  lp="$(dirname "$target")/.$(basename "$target").lock"
  mkdir -p "$(dirname "$target")"
  if ! command -v flock >/dev/null 2>&1; then return 0; fi   # util-linux missing: no lock
  while :; do
    exec {NR_LOCK_FD}<>"$lp"
    if ! flock -n "$NR_LOCK_FD"; then
      echo "error: $target is being written by another command ($(head -c 300 "$lp" 2>/dev/null || true)); nothing was written: wait for it to finish, or choose another output" >&2
      exit 2
    fi
    # the previous holder removes the file when done: hold the lock of the file that is there now
    [ "$(stat -c %i "$lp" 2>/dev/null || true)" = "$(stat -L -c %i "/proc/self/fd/$NR_LOCK_FD")" ] && break
    exec {NR_LOCK_FD}>&-
  done
  printf 'pid %s: %s\n' "$$" "$0 $*" >"/proc/self/fd/$NR_LOCK_FD"
  NR_LOCK_FILES+=("$lp")
  trap 'rm -f "${NR_LOCK_FILES[@]}"' EXIT
}
NR_LOCK_FILES=()

# nr_clip CLIP_DIR [PROFILE]: sets RAW, PROFILE, W, H, FPS, FRAMES and SRC (filesrc ! rawvideoparse !
# nrvalidity ! nrcrosstalk mode=$CROSSTALK) from CLIP_DIR/clip.json; PROFILE defaults to the clip's
# camera.json. CROSSTALK: kernel (the default, as nrhdr batch) or lut (live: ~10x faster) or off.
nr_clip() {
  local dir="$1" prof="${2:-}"
  if [ ! -f "$dir/clip.json" ]; then
    echo "error: $dir is not a clip folder (no clip.json); make one with: nrhdr simulate -o $dir" >&2
    exit 2
  fi
  local vals
  vals="$(nr_py - "$dir/clip.json" <<'PY'
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
       "mode=${MODE:-threshold}" ! nrcrosstalk "mode=${CROSSTALK:-kernel}")
}

# nr_out DIR EXT: lock and make the output folder of a frame sequence (frame_%05d.EXT). An existing sequence
# there is refused (old and new frames would mix) unless OVERWRITE=true, which deletes only its
# frame_NNNNN.EXT files.
nr_out() {
  local dir="$1" ext="$2" old
  nr_lock "$dir"
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

# nr_launch ARGS...: run `"$NRHDR" launch ARGS` for a script that must do something after the pipeline or holds
# a lock (else `exec "$NRHDR" launch ...`: the signal then reaches nrhdr directly). SIGINT, SIGTERM and SIGHUP to the
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

# nr_refuse PATH: refuse an existing output file unless OVERWRITE=true
nr_refuse() {
  if [ -e "$1" ] && [ "${OVERWRITE:-false}" != "true" ]; then
    echo "error: $1 exists: choose another name or set OVERWRITE=true" >&2; exit 2
  fi
}

# The preview sink into the array SINKV: $SINK when set (its words), else the display's sink (autovideosink in a
# Wayland display; under X11 alone an X sink, since autovideosink tries waylandsink first, which crashes without
# XDG_RUNTIME_DIR), else a fakesink with a video sink's defaults (sync, QoS events upstream, frames more than
# 20 ms late dropped), said on stderr.
nr_display_sink() {
  if [ -n "${SINK:-}" ]; then
    read -r -a SINKV <<<"$SINK"
  elif [ -n "${WAYLAND_DISPLAY:-}" ] && [ -d "${XDG_RUNTIME_DIR:-/nonexistent}" ]; then
    SINKV=(autovideosink sync=true)
  elif [ -n "${DISPLAY:-}" ]; then
    SINKV=(autovideosink sync=true)
    local s
    for s in xvimagesink ximagesink; do
      if gst-inspect-1.0 --exists "$s"; then SINKV=("$s" sync=true); break; fi
    done
  else
    echo "$(basename "$0"): no display (DISPLAY unset, no Wayland display with XDG_RUNTIME_DIR): the frames go" \
         "to fakesink" >&2
    SINKV=(fakesink sync=true qos=true max-lateness=20000000)
  fi
}
