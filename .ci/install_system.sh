#!/usr/bin/env bash
# Install the Debian packages of the full test run: headless QGIS for the plugin tests (tests/qgis, marker `qgis`), only what is missing (idempotent).
#   qgis python3-qgis : /usr/bin/qgis_process.bin and PyQGIS (Debian 12: QGIS 3.22 LTR)
#   proj-data         : /usr/share/proj/egm96_15.gtx (EGM96 geoid, used by geocd and by QGIS)
# Runs as root, or through sudo when available; without either it says what to install and exits 0 so that
# the QGIS tests skip (with their reason) instead of failing the run.
set -euo pipefail
need=()
[ -x /usr/bin/qgis_process.bin ] || need+=(qgis)
/usr/bin/python3 -c "import qgis.core" >/dev/null 2>&1 || need+=(python3-qgis)
[ -f /usr/share/proj/egm96_15.gtx ] || need+=(proj-data)
if [ "${#need[@]}" -eq 0 ]; then
  echo "install_system: $(QT_QPA_PLATFORM=offscreen /usr/bin/qgis_process.bin --version 2>/dev/null | grep -m1 -o 'QGIS [0-9.]*' || true) already installed"
  exit 0
fi
SUDO=""
if [ "$(id -u)" != "0" ]; then
  if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    SUDO="sudo -n"
  else
    echo "install_system: need root to install ${need[*]} (apt-get install -y --no-install-recommends ${need[*]}); skipping"
    exit 0
  fi
fi
echo "install_system: installing ${need[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq || true
$SUDO apt-get install -y -qq --no-install-recommends "${need[@]}"
QT_QPA_PLATFORM=offscreen /usr/bin/qgis_process.bin --version 2>/dev/null | grep -m1 -o 'QGIS [0-9.]*' || true
