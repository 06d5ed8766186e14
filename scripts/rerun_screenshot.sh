#!/usr/bin/env bash
# A screenshot of the Rerun viewer on a run's recording, as in the README (docs/img/rerun_main_job.jpg):
#   scripts/rerun_screenshot.sh outputs/runs/<time>/run.rrd docs/img/rerun_main_job.jpg
# The native viewer (rerun-sdk, scripts/setup.sh --dev) draws on a virtual display with a software
# renderer; on Debian: apt-get install xvfb xdotool mesa-vulkan-drivers libgl1-mesa-dri.
set -euo pipefail
cd "$(dirname "$0")/.."
recording=${1:?give a run.rrd}
out=${2:?give the image to write (.jpg)}
size=${SIZE:-1600x1000}
display=:${DISPLAY_NUMBER:-97}

shot=$(mktemp --suffix=.png)
Xvfb "$display" -screen 0 "${size}x24" -nolisten tcp &
xvfb=$!
trap 'kill "$xvfb" 2>/dev/null; rm -f "$shot"' EXIT
sleep 2
DISPLAY=$display xdotool mousemove "${size%x*}" "${size#*x}"  # the pointer in a corner: no tooltip
# the viewer opens the recording at its end (the blueprint follows it), shoots once it has drawn, and quits
DISPLAY=$display XDG_RUNTIME_DIR=$(mktemp -d) \
  .venv/bin/rerun "$recording" --window-size "$size" --screenshot-to "$shot" >/dev/null 2>&1
.venv/bin/python - "$shot" "$out" "$size" <<'PY'
import sys

import cv2

shot, out, size = sys.argv[1], sys.argv[2], sys.argv[3]
width, height = map(int, size.split("x"))
image = cv2.imread(shot)  # the viewer shoots at twice the window's pixels
image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
cv2.imwrite(out, image, [cv2.IMWRITE_JPEG_QUALITY, 85])
print(out, image.shape[1], "x", image.shape[0])
PY
