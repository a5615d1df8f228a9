#!/usr/bin/env bash
# Make a stand-in for the Dockerfile's base image (python:3.11-slim) in podman's local storage, from Debian
# bookworm's own packages, for machines that reach Debian's mirror but not a container registry. See
# scripts/container_smoke.sh for how the stand-in differs from the official image. Does nothing when an image
# of that name is already there. Installs podman (Debian's) when it is missing. Run as root (debootstrap and podman import need it).
set -euo pipefail
BASE=${BASE:-docker.io/library/python:3.11-slim}
command -v podman >/dev/null || { apt-get update -qq && apt-get install -y -qq podman >/dev/null; }
podman image exists "$BASE" && { echo "== base $BASE present"; exit 0; }
if timeout 60 podman pull -q "$BASE" >/dev/null 2>&1; then echo "== pulled $BASE"; exit 0; fi
command -v debootstrap >/dev/null || { apt-get update -qq && apt-get install -y -qq debootstrap >/dev/null; }
mirror=${DEBIAN_MIRROR:-$(sed -n 's/^URIs: *//p' /etc/apt/sources.list.d/*.sources 2>/dev/null | head -1)}
mirror=${mirror:-http://deb.debian.org/debian}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
echo "== registry unreachable: stand-in $BASE from $mirror"
debootstrap --variant=minbase --include=python3,python3-venv,python-is-python3,ca-certificates \
  bookworm "$tmp/rootfs" "$mirror" >"$tmp/debootstrap.log" 2>&1 || { tail -20 "$tmp/debootstrap.log"; exit 1; }
chroot "$tmp/rootfs" sh -c 'apt-get clean && rm -rf /var/lib/apt/lists/*'
tar --numeric-owner -C "$tmp/rootfs" -cf - . | podman import \
  --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  --change 'ENV LANG=C.UTF-8' --change 'CMD ["python3"]' - "$BASE" >/dev/null
echo "== stand-in $BASE imported"
