#!/usr/bin/env bash
# Make a Debian bookworm base image (Python 3.11 + Open3D's system libraries) without any registry:
# debootstrap from the Debian mirror, trim, `docker import`. Needs root, debootstrap and docker.
#   docker/base.sh [TAG]        (default cosim-base:bookworm)
# Then: make image BASE=cosim-base:bookworm
set -euo pipefail
TAG="${1:-cosim-base:bookworm}"
MIRROR="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
# python3-venv for the image's virtual environment; the rest is what the Open3D and SUMO wheels link
# against (the same list as the Makefile's SYSTEM_LIBS).
INCLUDE="python3,python3-venv,libusb-1.0-0,libgl1,libegl1,libgomp1,libatomic1,libxrender1"
[ "$(id -u)" = 0 ] || { echo "docker/base.sh: debootstrap needs root" >&2; exit 1; }
command -v debootstrap >/dev/null || { echo "docker/base.sh: debootstrap missing (apt-get install debootstrap)" >&2; exit 1; }
root="$(mktemp -d /tmp/cosim-base.XXXXXX)"
trap 'rm -rf "$root"' EXIT
debootstrap --variant=minbase --include="$INCLUDE" bookworm "$root" "$MIRROR" >"$root.log" 2>&1 \
  || { tail -20 "$root.log" >&2; rm -f "$root.log"; exit 1; }
rm -f "$root.log"
# Downloaded packages, apt lists, documentation: nothing the image needs at run time.
rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/* "$root"/usr/share/doc/* \
       "$root"/usr/share/man/* "$root"/usr/share/info/* "$root"/var/log/*.log
tar -C "$root" -c . | docker import --change 'ENV LANG=C.UTF-8' - "$TAG" >/dev/null
echo "$TAG"
