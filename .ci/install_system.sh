#!/usr/bin/env bash
# Install the Debian packages geocd's tests need, only when missing (idempotent).
#   proj-data: EGM96 geoid grid (/usr/share/proj/egm96_15.gtx) for vertical datum conversion
#   qgis python3-qgis: headless QGIS for the plugin tests (qgis_process.bin)
set -euo pipefail
SUDO=""
if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
need=()
[ -f /usr/share/proj/egm96_15.gtx ] || need+=(proj-data)
[ -x /usr/bin/qgis_process.bin ] || need+=(qgis python3-qgis)
if [ "${#need[@]}" -gt 0 ]; then
  echo "installing system packages: ${need[*]}"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq || true
  $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}"
fi
