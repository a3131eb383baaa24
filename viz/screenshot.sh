#!/usr/bin/env bash
# Renders a rall recording in the real rerun viewer, headless, and saves a PNG.
#
#   viz/screenshot.sh RECORDING.rrd OUT.png [WIDTHxHEIGHT]
#
# Needs: the viewer (pip install "rerun-sdk==0.36.3"), python3, Xvfb and a Vulkan driver
# that runs without a GPU (Debian: apt-get install xvfb mesa-vulkan-drivers, which
# brings lavapipe). Xvfb runs with `-extension Composite` (Composite disabled):
# with Composite on, the viewer's window stays black. rerun's GL backend refuses
# the R32Float textures the viewer needs, so the renderer is Vulkan.
# See viz/README.md.
set -euo pipefail

if [ $# -lt 2 ] || [ $# -gt 3 ]; then
  echo "usage: $0 RECORDING.rrd OUT.png [WIDTHxHEIGHT]" >&2
  exit 2
fi
rrd="$1"
out="$2"
size="${3:-1600x900}"
[ -f "$rrd" ] || { echo "$0: no recording at $rrd" >&2; exit 1; }
for tool in rerun Xvfb; do
  if ! command -v "$tool" >/dev/null 2>&1; then
    case "$tool" in
      rerun) hint='pip install "rerun-sdk==0.36.3"' ;;
      Xvfb) hint='apt-get install xvfb mesa-vulkan-drivers' ;;
    esac
    echo "$0: $tool is not on PATH (install it: $hint)" >&2
    exit 1
  fi
done
rerun analytics disable >/dev/null 2>&1 || true

# A free display number.
display=99
while [ -e "/tmp/.X11-unix/X$display" ] || [ -e "/tmp/.X$display-lock" ]; do
  display=$((display + 1))
done
# The screen is twice the window's size (plus two pixels). X starts the pointer at
# the screen's centre, which the viewer's window covers (at a scale factor of 2 it
# fills the screen), and its hover tooltip would show in the picture: the pointer is
# moved to the screen's bottom-right pixel, outside the window, before the viewer
# starts. `-noreset` keeps it there: Xvfb resets the pointer when its last client
# disconnects.
width="${size%x*}"
height="${size#*x}"
screen="$((2 * width + 2))x$((2 * height + 2))"
Xvfb ":$display" -screen 0 "${screen}x24" -extension Composite -noreset >/dev/null 2>&1 &
xvfb_pid=$!
trap 'kill "$xvfb_pid" 2>/dev/null || true' EXIT
for _ in $(seq 50); do
  [ -e "/tmp/.X11-unix/X$display" ] && break
  sleep 0.1
done
# XWarpPointer through libX11 (no xdotool needed).
DISPLAY=":$display" python3 - "$((2 * width + 1))" "$((2 * height + 1))" <<'PY' || echo "$0: could not move the pointer; a tooltip may show" >&2
import ctypes, sys
x11 = ctypes.CDLL("libX11.so.6")
x11.XOpenDisplay.restype = ctypes.c_void_p
x11.XDefaultRootWindow.restype = ctypes.c_ulong
x11.XDefaultRootWindow.argtypes = [ctypes.c_void_p]
x11.XWarpPointer.argtypes = [ctypes.c_void_p, ctypes.c_ulong, ctypes.c_ulong] + [ctypes.c_int] * 2 + [ctypes.c_uint] * 2 + [ctypes.c_int] * 2
x11.XFlush.argtypes = [ctypes.c_void_p]
dpy = x11.XOpenDisplay(None)
if not dpy:
    raise SystemExit(1)
x, y = int(sys.argv[1]), int(sys.argv[2])
x11.XWarpPointer(dpy, 0, x11.XDefaultRootWindow(dpy), 0, 0, 0, 0, x, y)
x11.XFlush(dpy)
PY

# lavapipe is the only Vulkan device here; WAYLAND_DISPLAY unset so winit uses X11.
mkdir -p "$(dirname "$out")"
rm -f "$out"
# rerun 0.36.3 saves the screenshot, then panics on the way out ("Failed to take
# store hub from the Viewer"): the exit status says nothing, the PNG does.
status=0
DISPLAY=":$display" WAYLAND_DISPLAY='' WGPU_BACKEND=vulkan \
  timeout 300 rerun --renderer vulkan --window-size "$size" --screenshot-to "$out" "$rrd" \
  || status=$?
if [ ! -s "$out" ]; then
  echo "$0: the viewer (exit status $status) wrote no $out" >&2
  exit 1
fi
echo "wrote $out"
