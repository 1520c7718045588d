#!/usr/bin/env bash
# Headless Chromium for the report's browser test (Debian/Ubuntu). Does nothing when it is already there.
set -euo pipefail
command -v chromium >/dev/null && exit 0
SUDO=$([ "$(id -u)" = 0 ] && echo "" || echo sudo)
$SUDO apt-get update -q
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q chromium
