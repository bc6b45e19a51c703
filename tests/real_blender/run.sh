#!/usr/bin/env bash
# The real-Blender suite: Blender 4.3.2 from Debian trixie (Python 3.13, numpy 2.x) in a rootfs.
#
#   tests/real_blender/run.sh ZIP [OUTDIR]
#
# Makes (or reuses) the rootfs, installs the built extension zip with Blender's own
# `blender --command extension install-file`, and runs checks.py inside `blender -b`.
# Needs root (debootstrap, chroot, mount). The rootfs is cached in $HRC_ROOTFS.
set -euo pipefail

ZIP=$(realpath "$1")
OUT=$(realpath -m "${2:-out/real_blender}")
HERE=$(cd "$(dirname "$0")" && pwd)
ROOTFS=${HRC_ROOTFS:-/var/cache/hybrid_raycast/trixie-blender}
PACKAGES="blender python3-numpy xvfb xauth libgl1-mesa-dri imagemagick xdotool"

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

mount -t proc proc "$ROOTFS/proc"
cleanup() { umount "$ROOTFS/proc" 2>/dev/null || true; }
trap cleanup EXIT

WORK=/tmp/hrc-test
rm -rf "$ROOTFS$WORK"
mkdir -p "$ROOTFS$WORK/user" "$OUT"
cp "$ZIP" "$ROOTFS$WORK/hybrid_raycast.zip"
cp "$HERE"/*.py "$ROOTFS$WORK/"
in_root() { chroot "$ROOTFS" env HOME=/root BLENDER_USER_RESOURCES=$WORK/user "$@"; }

echo "== $(in_root blender --version 2>/dev/null | head -1)"
echo "== install the zip with Blender's own command"
in_root blender --command extension install-file -r user_default -e $WORK/hybrid_raycast.zip
echo "== checks inside blender -b"
status=0
in_root blender -b --factory-startup --python-exit-code 1 --python $WORK/checks.py -- $WORK || status=$?
cp -r "$ROOTFS$WORK"/*.json "$OUT"/ 2>/dev/null || true
if [ "$status" != 0 ]; then
  echo "real-Blender suite FAILED (exit $status)" >&2
  exit "$status"
fi
echo "real-Blender suite passed; results in $OUT"
