#!/usr/bin/env bash
# Idempotent set-up for nrhdr on Debian 12: Debian packages (GStreamer, its Python plugin loader,
# PyGObject), a virtualenv made from /usr/bin/python3 with --system-site-packages (the plugin
# loader embeds the system Python), and the project installed into it. Safe to run repeatedly.
set -euo pipefail
cd "$(dirname "$0")/.."

PKGS=(gstreamer1.0-tools gstreamer1.0-python3-plugin-loader python3-gst-1.0 python3-gi
      gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-base
      gstreamer1.0-plugins-good python3-venv python3-dev libgomp1
      gstreamer1.0-plugins-bad gstreamer1.0-libav ffmpeg
      libaravis-0.8-0 aravis-tools gir1.2-aravis-0.8)
# plugins-bad: x265enc / h265parse (HDR10, HLG); libav: avdec_h265 (10-bit HEVC decode); ffmpeg: ffprobe and an
# independent decoder for the HDR round trip; Aravis: aravissrc (GenICam cameras) and its fake GigE Vision camera.
missing=()
for p in "${PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${missing[*]}"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv from /usr/bin/python3 (--system-site-packages)"
  /usr/bin/python3 -m venv --system-site-packages .venv
fi

stamp=.venv/.nrhdr-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "setup: installing nrhdr and its pip dependencies into .venv"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[dev]"
  touch "$stamp"
fi

# Compile the numba kernels once into numba's cache (next to the sources), so the first pipeline runs at
# full speed (`nrhdr warmup` = nrhdr_core.chain.warmup for every stage and setting). Again whenever a core
# source is newer than the stamp.
warm=.venv/.nrhdr-warm
if [ ! -f "$warm" ] || [ -n "$(find nrhdr_core -name '*.py' -newer "$warm" -print -quit)" ]; then
  echo "setup: compiling the numba kernels once (nrhdr warmup --cfa rggb: the monochrome and the colour chain)"
  .venv/bin/nrhdr warmup --cfa rggb
  touch "$warm"
fi
