#!/usr/bin/env bash
# Installs the Debian packages tsnav needs for headless OpenGL (EGL + Mesa), only when missing.
set -euo pipefail
need=()
for lib in libEGL.so.1 libGL.so.1; do
  ldconfig -p 2>/dev/null | grep -q "$lib" || need+=("$lib")
done
ls /usr/lib/*/dri/swrast_dri.so >/dev/null 2>&1 || need+=(dri)
ls /usr/lib/*/libEGL_mesa.so.0 >/dev/null 2>&1 || need+=(egl-mesa)
if [ ${#need[@]} -eq 0 ]; then exit 0; fi
echo "installing EGL/Mesa packages (missing: ${need[*]})"
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 >/dev/null
