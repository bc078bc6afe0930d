#!/bin/sh
# Debian packages for offscreen rendering (EGL via Mesa, OSMesa as a fallback). Installed only when
# missing and only when we can (root or passwordless sudo); otherwise print what to install.
missing=""
for p in libegl1 libgl1-mesa-dri libosmesa6; do
  dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
done
[ -z "$missing" ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
  echo "note: offscreen rendering needs EGL or OSMesa (Debian packages:$missing); reports will lack video without them"
  exit 0
fi
if [ "$(id -u)" = "0" ]; then SUDO=""; elif sudo -n true 2>/dev/null; then SUDO="sudo -n"; else
  echo "note: please install$missing (apt-get) for offscreen rendering"; exit 0
fi
echo "installing$missing for offscreen rendering"
$SUDO apt-get update -qq >/dev/null 2>&1 || true
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null 2>&1 || \
  echo "note: could not install$missing; reports will lack video"
exit 0
