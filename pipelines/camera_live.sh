#!/usr/bin/env bash
# Live camera -> HDR preview, or recording (linear EXR frames + the raw frames) with a preview (docs/CAMERAS.md).
#   pipelines/camera_live.sh preview
#   pipelines/camera_live.sh record OUT_DIR
# CAMERA: a GenICam camera (GigE Vision / USB3 Vision, through aravissrc): its IP address (the reliable choice on
#   a host with several network interfaces) or name, empty = the first found; or a V4L2 device (/dev/videoN,
#   through v4l2src). PROFILE (required): the camera profile; its width x height is the frame size asked of the
#   camera, its bit depth, white level, alignment and packing say what the GRAY16_LE words hold (docs/PROFILE.md).
# FRAMES: frames to capture (default: until stopped; Ctrl-C, SIGTERM or SIGHUP end with EOS, files finished).
# Camera settings, GenICam: PIXEL_FORMAT (PixelFormat, e.g. Mono16, Mono12, Mono12Packed; default: what
#   GRAY16_LE negotiates), EXPOSURE (us), GAIN (dB), FPS (frames/s, in the caps), FEATURES ("Feature=value ..."
#   for anything else); V4L2: FPS and V4L2_CONTROLS (v4l2src extra-controls, e.g. "c,exposure_time_absolute=100").
#   FORMAT=GRAY8 takes 8-bit frames and widens them with videoconvert (code * 257: a profile with bit_depth 8 and
#   alignment msb reads them back exactly). A colour camera (the profile's cfa a Bayer phase): GRAY16_LE carries
#   its 10-16-bit mosaic; FORMAT=BAYER takes 8-bit video/x-bayer in the profile's phase (bit_depth 8 profile;
#   GenICam BayerRG8/BG8/GR8/GB8: the only Bayer caps aravissrc and v4l2src have), RGB frames come out.
# record: every frame through the chain into OUT_DIR/frame_%05d.exr (linear, with the state channel), and the
#   raw camera frames with their caps and timestamps into OUT_DIR/raw.gdp (RAW=false: not written; replay it
#   with `filesrc location=raw.gdp ! gdpdepay ! nrvalidity profile=...`). The preview branch is leaky (drops
#   frames when late), the recording branches are not (10 s of frames queue up when the chain is slower).
# Environment: METHOD (auto: per frame the best reconstruction that keeps up), PRESET (fast), CROSSTALK (lut),
#   MODE (threshold), SINK (default autovideosink with a display, else a QoS fakesink), OVERWRITE (true: replace
#   an earlier recording in OUT_DIR), VERBOSE=1 (gst-launch -m), NRHDR.
source "$(dirname "${BASH_SOURCE[0]}")/common.sh"
case "${1:-}" in
  -h|--help|"") sed -n '2,23p' "$0"; [ -n "${1:-}" ]; exit $?;;
  preview|record) ACTION="$1";;
  *) echo "error: unknown mode '$1': use preview or record OUT_DIR" >&2; exit 2;;
esac
if [ -z "${PROFILE:-}" ]; then
  echo "error: set PROFILE to the camera's profile (nrhdr profile / nrhdr calibrate; docs/CAMERAS.md)" >&2; exit 2
fi
# the frame size the profile needs (the profile is checked here: a bad one is refused before the camera opens)
read -r W H CFA < <(nr_py - "$PROFILE" <<'PY' || echo "- - -"
import sys
from nrhdr_core import profile
try:
    p = profile.load(sys.argv[1])
except profile.ProfileError as e:
    sys.exit(f"error: {e}")
print(p.width, p.height, p.cfa)
PY
)
[ "$W" = "-" ] && exit 2
CAMERA="${CAMERA:-}" NBUF="${FRAMES:--1}" IN_FORMAT="${FORMAT:-GRAY16_LE}"
case "$IN_FORMAT" in
  GRAY16_LE|GRAY8) CAPS="video/x-raw,format=$IN_FORMAT,width=$W,height=$H${FPS:+,framerate=$FPS/1}";;
  BAYER)
    if [ "$CFA" = none ]; then
      echo "error: FORMAT=BAYER needs a colour profile, but $PROFILE is monochrome (cfa none)" >&2; exit 2
    fi
    CAPS="video/x-bayer,format=$CFA,width=$W,height=$H${FPS:+,framerate=$FPS/1}";;
  *) echo "error: FORMAT must be GRAY16_LE, GRAY8 or BAYER, got $IN_FORMAT" >&2; exit 2;;
esac
if [[ "$CAMERA" == /dev/* ]]; then
  if [ ! -e "$CAMERA" ]; then
    echo "error: V4L2 device $CAMERA not found (no such file; v4l2-ctl --list-devices lists the devices)" >&2; exit 2
  fi
  if [ -n "${EXPOSURE:-}${GAIN:-}${PIXEL_FORMAT:-}${FEATURES:-}" ]; then
    echo "error: EXPOSURE, GAIN, PIXEL_FORMAT and FEATURES are GenICam settings; for $CAMERA set V4L2_CONTROLS" >&2
    exit 2
  fi
  CAM=(v4l2src "device=$CAMERA" "num-buffers=$NBUF")
  [ -n "${V4L2_CONTROLS:-}" ] && CAM+=("extra-controls=$V4L2_CONTROLS")
else
  CAM=(aravissrc "num-buffers=$NBUF")
  [ -n "$CAMERA" ] && CAM+=("camera-name=$CAMERA")
  [ -n "${EXPOSURE:-}" ] && CAM+=("exposure=$EXPOSURE")
  [ -n "${GAIN:-}" ] && CAM+=("gain=$GAIN")
  FEAT="${PIXEL_FORMAT:+PixelFormat=$PIXEL_FORMAT }${FEATURES:-}"
  [ -n "$FEAT" ] && CAM+=("features=$FEAT")
fi
CAM+=(! "$CAPS")
[ "$IN_FORMAT" = GRAY8 ] && CAM+=(! videoconvert ! "video/x-raw,format=GRAY16_LE")
# record: qos=false, the recording never drops a frame because the preview sink is late (its QoS events
# travel up through the tee); the preview's own branch drops instead (leaky queue, nrtonemap's QoS)
QOS=$([ "$ACTION" = record ] && echo false || echo true)
CHAIN=(nrvalidity "profile=$PROFILE" "mode=${MODE:-threshold}" "qos=$QOS" ! nrcrosstalk "mode=${CROSSTALK:-lut}"
       "qos=$QOS" ! nrreconstruct "method=${METHOD:-auto}" "preset=${PRESET:-fast}" "qos=$QOS")
nr_display_sink
PREVIEW=(nrtonemap ! videoconvert ! "${SINKV[@]}")
ARGS=()
[ "${VERBOSE:-0}" = 1 ] && ARGS+=(-m)
if [ "$ACTION" = preview ]; then
  NRHDR_REPORT_DROPS=1 nr_launch "${ARGS[@]}" "${CAM[@]}" ! queue leaky=downstream max-size-buffers=2 \
    ! "${CHAIN[@]}" ! "${PREVIEW[@]}"
  exit 0
fi
OUT="${2:-}"
if [ -z "$OUT" ]; then echo "error: record needs the output folder: $0 record OUT_DIR" >&2; exit 2; fi
nr_out "$OUT" exr
KEEP=(queue max-size-buffers=0 max-size-bytes=0 max-size-time=10000000000)
RAWV=()
if [ "${RAW:-true}" = true ]; then
  nr_refuse "$OUT/raw.gdp"
  RAWV=(t. ! "${KEEP[@]}" ! gdppay ! filesink "location=$OUT/raw.gdp")
fi
NRHDR_REPORT_DROPS=1 nr_launch "${ARGS[@]}" "${CAM[@]}" ! tee name=t "${RAWV[@]}" \
  t. ! "${KEEP[@]}" ! "${CHAIN[@]}" ! tee name=h \
  h. ! "${KEEP[@]}" ! nrexrsink "location=$OUT/frame_%05d.exr" write-state=true \
  h. ! queue leaky=downstream max-size-buffers=2 ! "${PREVIEW[@]}"
