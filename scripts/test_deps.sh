#!/bin/sh
# Debian's headless Chromium for the tests that open reports in a browser (tests/helpers.py: chromium_check).
# Installed only when missing and only when we can (root or passwordless sudo); otherwise those tests skip
# and the test summary counts them ("skipped tests: N").
command -v chromium >/dev/null 2>&1 && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
  echo "note: the browser checks of the reports need Debian's chromium; they will be skipped"; exit 0
fi
if [ "$(id -u)" = "0" ]; then SUDO=""; elif sudo -n true 2>/dev/null; then SUDO="sudo -n"; else
  echo "note: apt-get install chromium to run the browser checks of the reports; they will be skipped"; exit 0
fi
echo "installing chromium for the browser checks of the reports"
$SUDO apt-get update -qq >/dev/null 2>&1 || true
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends chromium >/dev/null 2>&1 || \
  echo "note: could not install chromium; the browser checks of the reports will be skipped"
exit 0
