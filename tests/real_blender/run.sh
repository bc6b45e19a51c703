#!/usr/bin/env bash
# The real-Blender suite: Blender 4.3.2 from Debian trixie (Python 3.13, numpy 2.x) in a rootfs.
#
#   tests/real_blender/run.sh ZIP [OUTDIR]
#
# Makes (or reuses) the rootfs, installs the built extension zip with Blender's own
# `blender --command extension install-file`, then
#   1. checks.py inside `blender -b` (operators, API, calibration, numpy 2; saves .blend files),
#   2. check_cli.py: `blender -b FILE.blend -c hybrid_raycast ...`, exit codes and JSON,
#   3. the GUI under Xvfb: the sidebar's "Hybrid RT" tab and its Analyze button are clicked
#      with xdotool; the screenshot (OUTDIR/screenshot.png) shows the panel with a decision;
#   4. Esc cancels a running calibration started from the panel (OUTDIR/cancelled.png),
#      leaving the calibration file and the results as they were.
# Needs root (debootstrap, chroot, mount). The rootfs is cached in $HRC_ROOTFS.
set -euo pipefail

ZIP=$(realpath "$1")
OUT=$(realpath -m "${2:-out/real_blender}")
HERE=$(cd "$(dirname "$0")" && pwd)
ROOTFS=${HRC_ROOTFS:-/var/cache/hybrid_raycast/trixie-blender}
PACKAGES="blender python3-numpy xvfb xauth libgl1-mesa-dri imagemagick xdotool"
DISPLAY_NUM=${HRC_DISPLAY:-99}

if [ "$(id -u)" != 0 ]; then
  echo "real-Blender suite: needs root for debootstrap/chroot; skipped" >&2
  exit 0
fi

if [ ! -f "$ROOTFS/.hrc-ready" ] || [ "$(cat "$ROOTFS/.hrc-ready")" != "$PACKAGES" ]; then
  echo "== making the Debian trixie rootfs in $ROOTFS (about a minute)"
  command -v debootstrap >/dev/null || DEBIAN_FRONTEND=noninteractive apt-get install -y -q debootstrap >/dev/null
  rm -rf "$ROOTFS.tmp"
  mkdir -p "$(dirname "$ROOTFS")"
  debootstrap --variant=minbase trixie "$ROOTFS.tmp" http://deb.debian.org/debian >/dev/null
  mount -t proc proc "$ROOTFS.tmp/proc"
  trap 'umount "$ROOTFS.tmp/proc" 2>/dev/null || true' EXIT
  chroot "$ROOTFS.tmp" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $PACKAGES >/dev/null
  chroot "$ROOTFS.tmp" apt-get clean
  umount "$ROOTFS.tmp/proc"
  trap - EXIT
  echo "$PACKAGES" > "$ROOTFS.tmp/.hrc-ready"
  rm -rf "$ROOTFS"
  mv "$ROOTFS.tmp" "$ROOTFS"
fi

WORK=/tmp/hrc-test
XVFB_PID=""
BLENDER_PID=""
mount -t proc proc "$ROOTFS/proc"
cleanup() {
  # only the processes this script started, by their ids
  [ -n "$BLENDER_PID" ] && kill "$BLENDER_PID" 2>/dev/null || true
  [ -n "$XVFB_PID" ] && kill "$XVFB_PID" 2>/dev/null || true
  sleep 1
  umount "$ROOTFS/proc" 2>/dev/null || true
}
trap cleanup EXIT

rm -rf "$ROOTFS$WORK"
mkdir -p "$ROOTFS$WORK/user" "$OUT"
cp "$ZIP" "$ROOTFS$WORK/hybrid_raycast.zip"
cp "$HERE"/*.py "$ROOTFS$WORK/"
in_root() { chroot "$ROOTFS" env HOME=/root BLENDER_USER_RESOURCES=$WORK/user "$@"; }
collect() { cp -r "$ROOTFS$WORK"/*.json "$ROOTFS$WORK"/*.png "$OUT"/ 2>/dev/null || true;
            [ -d "$ROOTFS$WORK/cli_out" ] && cp -r "$ROOTFS$WORK/cli_out" "$OUT"/ || true; }
fail() { collect; echo "real-Blender suite FAILED: $1" >&2; exit 1; }

echo "== $(in_root blender --version 2>/dev/null | head -1)"
echo "== install the zip with Blender's own command (enabled in the user preferences)"
in_root blender --command extension install-file -r user_default -e $WORK/hybrid_raycast.zip

echo "== 1. checks inside blender -b"
status=0
in_root blender -b --factory-startup --python-exit-code 1 --python $WORK/checks.py -- $WORK || status=$?
[ "$status" = 0 ] || fail "checks.py exited $status"

echo "== 2. the command line: blender -b FILE.blend -c hybrid_raycast ..."
in_root python3 $WORK/check_cli.py $WORK || fail "check_cli.py"

echo "== 3. the GUI under Xvfb: click the Hybrid RT tab and Analyze"
rm -f "$ROOTFS/tmp/.X$DISPLAY_NUM-lock"
in_root sh -c "Xvfb :$DISPLAY_NUM -screen 0 1600x1000x24 -nolisten tcp >$WORK/xvfb.log 2>&1 & echo \$! >$WORK/xvfb.pid"
XVFB_PID=$(cat "$ROOTFS$WORK/xvfb.pid")
sleep 2
in_root env LIBGL_ALWAYS_SOFTWARE=1 DISPLAY=:$DISPLAY_NUM sh -c \
  "blender --factory-startup $WORK/demo.blend --python $WORK/gui_startup.py -- $WORK >$WORK/gui.log 2>&1 & echo \$! >$WORK/blender.pid"
BLENDER_PID=$(cat "$ROOTFS$WORK/blender.pid")
x() { in_root env DISPLAY=:$DISPLAY_NUM xdotool "$@"; }
status_field() { in_root python3 -c "import json,sys; print(json.load(open('$WORK/gui_status.json')).get('$1'))" 2>/dev/null || echo none; }
for _ in $(seq 60); do [ -f "$ROOTFS$WORK/gui_layout.json" ] && [ -f "$ROOTFS$WORK/gui_status.json" ] && break; sleep 1; done
[ -f "$ROOTFS$WORK/gui_layout.json" ] || fail "the GUI did not start (see $OUT/gui.log)"
cp "$ROOTFS$WORK/gui.log" "$OUT/" 2>/dev/null || true
# screen coordinates of the sidebar (Blender's y grows upwards, X11's downwards)
read -r SB_LEFT SB_RIGHT SB_TOP SCALE <<<"$(in_root python3 -c "
import json; L = json.load(open('$WORK/gui_layout.json'))
w, s = L['window'], L['sidebar']
print(w['x'] + s['x'], w['x'] + s['x'] + s['width'], w['height'] - (s['y'] + s['height']), L['ui_scale'])")"
echo "   sidebar x $SB_LEFT-$SB_RIGHT, top $SB_TOP, ui scale $SCALE"
# the tabs run down the sidebar's right edge: click down it until Hybrid RT is active
TAB_X=$((SB_RIGHT - 13))
for dy in $(seq 20 12 400); do
  [ "$(status_field category)" = "Hybrid RT" ] && break
  x mousemove "$TAB_X" $((SB_TOP + dy)) click 1
  sleep 0.8
done
[ "$(status_field category)" = "Hybrid RT" ] || fail "could not open the Hybrid RT tab"
echo "   Hybrid RT tab open"
in_root env DISPLAY=:$DISPLAY_NUM import -window root $WORK/before_click.png
# Analyze: the wide button below the ray budget (measured on 4.3.2: 164 px below the
# sidebar's top at UI scale 1); try around it until the analysis runs
ANALYZE_X=$(( (SB_LEFT * 55 + SB_RIGHT * 45) / 100 ))
BASE_Y=$(in_root python3 -c "print(round($SB_TOP + 164 * $SCALE))")
clicked=""
for off in 0 -8 8 -16 16; do
  x mousemove "$ANALYZE_X" $((BASE_Y + off)) click 1
  sleep 1.5
  if [ "$(status_field running)" = "True" ] || [ "$(status_field has_results)" = "True" ]; then
    clicked="$ANALYZE_X,$((BASE_Y + off))"; break
  fi
done
[ -n "$clicked" ] || fail "clicking around ($ANALYZE_X, $BASE_Y) did not start the analysis"
echo "   clicked Analyze at $clicked"
for _ in $(seq 120); do [ "$(status_field has_results)" = "True" ] && break; sleep 0.5; done
DECISION=$(status_field decision)
[ "$(status_field has_results)" = "True" ] || fail "no decision 60 s after the click"
# move the pointer over the panel and away so the sidebar redraws in its final state
x mousemove $((SB_LEFT + 40)) $((BASE_Y + 200)); sleep 0.5; x mousemove 400 500; sleep 1.5
in_root env DISPLAY=:$DISPLAY_NUM import -window root $WORK/screenshot.png
echo "   the panel shows $DECISION; screenshot $OUT/screenshot.png"
cp "$ROOTFS$WORK/gui_status.json" "$ROOTFS$WORK/gui_result.json"

echo "== 4. Esc cancels: start Calibrate (full scale) from the panel, press Esc"
CAL="$ROOTFS$WORK/user/extensions/.user/user_default/hybrid_raycast/calibration.json"
before=$(stat -c %Y.%s "$CAL" 2>/dev/null || echo none)
GEAR_Y=${clicked#*,}
x mousemove $((SB_RIGHT - 49)) "$GEAR_Y" click 1
for _ in $(seq 20); do [ "$(status_field running)" = "True" ] && break; sleep 0.25; done
[ "$(status_field running)" = "True" ] || fail "the calibrate button did not start a calibration"
x mousemove 400 500; sleep 0.3
x key Escape
for _ in $(seq 20); do [ "$(status_field running)" = "False" ] && break; sleep 0.25; done
[ "$(status_field running)" = "False" ] || fail "Esc did not cancel the calibration"
sleep 3  # the worker thread stops at its next progress call; nothing may be saved after it
after=$(stat -c %Y.%s "$CAL" 2>/dev/null || echo none)
[ "$before" = "$after" ] || fail "a cancelled calibration changed $CAL ($before -> $after)"
[ "$(status_field decision)" = "$DECISION" ] || fail "cancelling changed the decision"
in_root env DISPLAY=:$DISPLAY_NUM import -window root $WORK/cancelled.png
echo "   Esc cancelled the calibration; calibration file and results unchanged"
collect
cp "$ROOTFS$WORK/gui.log" "$OUT/" 2>/dev/null || true
echo "real-Blender suite passed; results in $OUT"
