#!/usr/bin/env bash
# Container smoke test (`make image-test`; not part of `make test`): builds the Dockerfile with podman,
# then runs the image's filesystem under chroot as the image's own non-root user with the image's ENV,
# and checks GET /healthz, GET /readyz, one POST /v1/fixes (the README example), the HEALTHCHECK command,
# and that the SQLite session store file appears under the image's /app/var. Exits non-zero on any failure.
# No container engine or runtime is needed (no daemon, no network namespace): root, podman, curl, python3.
#
#   sudo scripts/container_smoke.sh            # build passive-locator:dev from this checkout, then run it
#   IMAGE=passive-locator:rc1 scripts/container_smoke.sh
#   BUILD=0 scripts/container_smoke.sh         # skip the build; smoke-test an existing $IMAGE
#   REF=HEAD scripts/container_smoke.sh        # build the committed tree, not the files on disk
#
# Environment:
#   IMAGE            tag to build and test (default passive-locator:dev)
#   BUILD            1 (default) builds first; 0 tests an existing $IMAGE
#   REF              empty (default): build this checkout as it is on disk, so uncommitted and untracked
#                    files under core/ and service/ go into the image; a git ref (HEAD, a tag): build that
#                    commit's tree, exported with `git archive` to a temporary directory
#   SMOKE_CA_BUNDLE  CA bundle mounted read-only over the base's /etc/ssl/certs/ca-certificates.crt in the
#                    build's RUN steps only (not committed to the image), for pip behind a TLS-intercepting
#                    proxy. Default: this host's /etc/ssl/certs/ca-certificates.crt; set it empty for none.
#                    Debian's pip (the stand-in base below) reads that file; the official image's pip reads
#                    its own certifi bundle instead, so there this only helps with a pip that uses the
#                    system store.
#   SMOKE_PORT       loopback port for the server (default: a free one)
#   SMOKE_MAX_STARTUP_S  seconds the server may take to answer /healthz (default 20; a start that compiles
#                    the kernels instead of loading the image's cache takes 75-140 s on a shared 2-core machine)
#
# The base image: FROM python:3.11-slim must already be in podman's local storage; the build never
# pulls (--pull=never). On a machine without registry access, make a stand-in from Debian's packages
# (Debian bookworm, like the official image), e.g. as root:
#
#   apt-get install -y debootstrap
#   tmp=$(mktemp -d)
#   debootstrap --variant=minbase --include=python3,python3-venv,python-is-python3,ca-certificates \
#       bookworm "$tmp/rootfs" "$DEBIAN_MIRROR"   # the mirror URL from /etc/apt/sources.list*
#   chroot "$tmp/rootfs" sh -c 'apt-get clean && rm -rf /var/lib/apt/lists/*'
#   tar --numeric-owner -C "$tmp/rootfs" -cf - . | podman import \
#       --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
#       --change 'ENV LANG=C.UTF-8' --change 'CMD ["python3"]' - docker.io/library/python:3.11-slim
#   rm -rf "$tmp"
#
# (The PATH change matters: the Dockerfile's `ENV PATH=/opt/venv/bin:$PATH` needs a PATH in the base's
# config, which the official image has and a bare `podman import` does not.) How the stand-in differs
# from the official image: Debian's python 3.11.2 at /usr/bin/python{,3} instead of the newest 3.11.x at
# /usr/local/bin/python; no pip on the PATH (only the venv's, Debian's pip 23.0.1 from python3-venv's
# bundled wheel); Debian's patched stdlib (sysconfig, ensurepip). The Dockerfile uses only
# `python -m venv` and /opt/venv/bin/*, which behave the same on both.
#
# How it runs the image: `podman image mount` is read-only, so the store could not be created there;
# the script mounts a created (never started) container instead, whose writable layer over the image
# plays the part a container's layer does, and removes that container afterwards (the image stays).
set -euo pipefail

IMAGE=${IMAGE:-passive-locator:dev}
BUILD=${BUILD:-1}
REF=${REF:-}
SMOKE_CA_BUNDLE=${SMOKE_CA_BUNDLE-/etc/ssl/certs/ca-certificates.crt}
repo=$(cd "$(dirname "$0")/.." && pwd)

say() { printf '== %s\n' "$*"; }
fail() { printf 'FAIL: %s\n' "$*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || fail "run as root (podman mount and chroot need it)"
for tool in podman curl python3 chroot; do
  command -v "$tool" >/dev/null || fail "$tool not found"
done

ctr="" mnt="" server_pid="" ctxdir="" log=$(mktemp)
cleanup() {
  if [ -n "$server_pid" ] && kill -0 "$server_pid" 2>/dev/null; then
    kill -TERM "$server_pid" 2>/dev/null || true
    sleep 2
    kill -KILL "$server_pid" 2>/dev/null || true
  fi
  if [ -n "$ctr" ]; then
    podman umount "$ctr" >/dev/null 2>&1 || true
    podman rm --force "$ctr" >/dev/null 2>&1 || true
  fi
  rm -f "$log"
  [ -z "$ctxdir" ] || rm -rf "$ctxdir"
}
trap cleanup EXIT

# --- build ----------------------------------------------------------------------------------------
if [ "$BUILD" = 1 ]; then
  build_args=(--isolation chroot --pull=never --format docker -t "$IMAGE")
  if [ -n "$SMOKE_CA_BUNDLE" ]; then
    [ -r "$SMOKE_CA_BUNDLE" ] || fail "SMOKE_CA_BUNDLE=$SMOKE_CA_BUNDLE is not readable"
    build_args+=(-v "$SMOKE_CA_BUNDLE:/etc/ssl/certs/ca-certificates.crt:ro")
  fi
  context=$repo
  if [ -n "$REF" ]; then
    ctxdir=$(mktemp -d)
    git -C "$repo" archive --format=tar "$REF" | tar -x -C "$ctxdir" || fail "git archive $REF failed"
    context=$ctxdir
    say "context: $REF = $(git -C "$repo" rev-parse --short "$REF") exported to $ctxdir"
  fi
  say "podman build ${build_args[*]} $context"
  start=$(date +%s)
  podman build "${build_args[@]}" "$context" || fail "podman build failed"
  say "build took $(( $(date +%s) - start )) s"
fi
podman image exists "$IMAGE" || fail "no image $IMAGE"
say "image $IMAGE: $(podman image inspect --format '{{.Id}} {{.Size}}' "$IMAGE" | awk '{printf "%.12s, %.0f MB", $1, $2/1e6}')"

# --- the image's config ---------------------------------------------------------------------------
user=$(podman image inspect --format '{{.Config.User}}' "$IMAGE")
workdir=$(podman image inspect --format '{{.Config.WorkingDir}}' "$IMAGE")
health=$(podman image inspect --format '{{if .Config.Healthcheck}}{{range .Config.Healthcheck.Test}}{{println .}}{{end}}{{end}}' "$IMAGE")
mapfile -t image_env < <(podman image inspect --format '{{range .Config.Env}}{{println .}}{{end}}' "$IMAGE" | sed '/^$/d')
say "USER=$user WORKDIR=$workdir"
printf '   ENV %s\n' "${image_env[@]}"
[[ "$user" =~ ^[0-9]+(:[0-9]+)?$ ]] || fail "USER '$user' is not numeric uid[:gid]"
uid=${user%%:*}
gid=${user#*:}; [ "$gid" != "$user" ] || gid=$uid
[ "$uid" != 0 ] || fail "image runs as root"
[ -n "$health" ] || fail "image has no HEALTHCHECK (built without --format docker?)"
store_url=$(printf '%s\n' "${image_env[@]}" | sed -n 's/^PASSIVE_LOCATOR_STORE=//p')
case "$store_url" in
  sqlite:////*) store_path=/${store_url#sqlite:////} ;;
  *) fail "PASSIVE_LOCATOR_STORE='$store_url' is not an absolute sqlite path" ;;
esac

# --- a writable view of the image -----------------------------------------------------------------
ctr=$(podman create --no-healthcheck --name "passive-locator-smoke-$$" "$IMAGE")
mnt=$(podman mount "$ctr")
say "rootfs $mnt"
for dev_path in src tests bench .venv; do
  for where in / "$workdir"/ /opt/venv/lib/python3*/site-packages/; do
    compgen -G "$mnt$where$dev_path" >/dev/null && fail "dev path in image: $where$dev_path"
  done
done
for installer in /opt/venv/bin/pip /usr/local/bin/pip /usr/local/lib/python3*/site-packages/pip \
                 /opt/venv/lib/python3*/site-packages/pip /opt/venv/lib/python3*/site-packages/setuptools \
                 /usr/local/lib/python3*/site-packages/setuptools; do
  compgen -G "$mnt$installer" >/dev/null && fail "installer in the runtime image: $installer"
done
say "no pip or setuptools in the runtime image"
[ ! -e "$mnt$store_path" ] || fail "store $store_path already exists in the image"
[ "$(stat -c %u "$mnt$(dirname "$store_path")")" = "$uid" ] || fail "$(dirname "$store_path") is not owned by uid $uid"

# --- run ------------------------------------------------------------------------------------------
port=${SMOKE_PORT:-$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')}
base=http://127.0.0.1:$port
say "serve on $base as $uid:$gid"
# shellcheck disable=SC2016  # $1/$@ expand in the inner shell
env -i "${image_env[@]}" HOME="$workdir" \
  chroot --userspec="$uid:$gid" "$mnt" /bin/sh -c 'cd "$1" && shift && exec "$@"' sh "$workdir" \
  passive-locator serve --host 127.0.0.1 --port "$port" >"$log" 2>&1 &
server_pid=$!
started=$SECONDS
for _ in $(seq 120); do
  kill -0 "$server_pid" 2>/dev/null || { cat "$log" >&2; fail "server exited"; }
  curl -fsS -o /dev/null "$base/healthz" 2>/dev/null && break
  sleep 0.5
done
# Loading the kernels from the image's numba cache takes seconds; compiling them all takes 75-140 s.
startup_s=$((SECONDS - started))
[ "$startup_s" -le "${SMOKE_MAX_STARTUP_S:-20}" ] \
  || fail "the server took ${startup_s} s to answer: it compiled its kernels (the image's numba cache was not used)"
say "answered after ${startup_s} s"

check() {  # check NAME EXPECTED-SUBSTRING curl-args...
  local name=$1 expect=$2 body
  shift 2
  body=$(curl -sS --max-time 30 -w '\nHTTP %{http_code}' "$@") || { cat "$log" >&2; fail "$name: curl failed"; }
  printf '%s -> %s\n' "$name" "$(printf '%s' "$body" | tr '\n' ' ' | cut -c 1-600)"
  [[ "$body" == *"HTTP 200" && "$body" == *"$expect"* ]] || { cat "$log" >&2; fail "$name: expected 200 with $expect"; }
}
check "GET /healthz" '"status":"ok"' "$base/healthz"
check "GET /readyz" '"status":"ready"' "$base/readyz"
check "POST /v1/fixes" '"position"' "$base/v1/fixes" -H 'content-type: application/json' -d '{
  "frame": "wgs84",
  "stations": [
    {"id": "rx-1", "position": {"lat_deg": 34.20, "lon_deg": 108.90, "alt_m": 400}},
    {"id": "rx-2", "position": {"lat_deg": 34.90, "lon_deg": 108.90, "alt_m": 1000}},
    {"id": "rx-3", "position": {"lat_deg": 34.50, "lon_deg": 109.40, "alt_m": 100}}],
  "measurements": [
    {"type": "bearing", "station_id": "rx-1", "azimuth_deg": 0.0,   "elevation_deg": 2.1, "sigma_azimuth_deg": 1, "sigma_elevation_deg": 1},
    {"type": "bearing", "station_id": "rx-2", "azimuth_deg": 180.0, "elevation_deg": 2.6, "sigma_azimuth_deg": 1, "sigma_elevation_deg": 1},
    {"type": "bearing", "station_id": "rx-3", "azimuth_deg": 270.3, "elevation_deg": 1.0, "sigma_azimuth_deg": 1, "sigma_elevation_deg": 1}]
}'

# The image's own HEALTHCHECK command (["CMD-SHELL", cmd]), inside the image, pointed at this port.
[ "$(printf '%s\n' "$health" | sed -n 1p)" = CMD-SHELL ] || fail "HEALTHCHECK is not the shell form this script runs"
health_cmd=$(printf '%s\n' "$health" | sed -n 2p | sed "s/127\.0\.0\.1:8080/127.0.0.1:$port/")
env -i "${image_env[@]}" chroot --userspec="$uid:$gid" "$mnt" /bin/sh -c "$health_cmd" \
  || fail "HEALTHCHECK command failed: $health_cmd"
say "HEALTHCHECK command exits 0"

[ -f "$mnt$store_path" ] || fail "store $store_path was not created"
say "store: $(stat -c '%n %s bytes, owner %u:%g, mode %a' "$mnt$store_path" | sed "s|^$mnt||")"

# --- stop -----------------------------------------------------------------------------------------
kill -TERM "$server_pid"
for _ in $(seq 40); do kill -0 "$server_pid" 2>/dev/null || break; sleep 0.25; done
kill -0 "$server_pid" 2>/dev/null && fail "server still running 10 s after SIGTERM"
status=0; wait "$server_pid" || status=$?
server_pid=""
grep -q 'Application shutdown complete' "$log" || { cat "$log" >&2; fail "no clean shutdown (exit $status)"; }
say "server stopped on SIGTERM (exit $status)"
python3 - "$mnt$store_path" <<'PY'
import sqlite3, sys
db = sqlite3.connect(f"file:{sys.argv[1]}?mode=ro", uri=True)
print("   store tables:", [r[0] for r in db.execute("select name from sqlite_master where type = 'table'")])
PY

# --- as deploy/ runs it: a read-only root filesystem and a fresh /tmp -------------------------------
# numba ignores a cache directory it cannot write: serve copies the image's into /tmp, says so, and loads
# its kernels from the copy (no compile: the image was built on this machine's CPU).
port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
say "serve on 127.0.0.1:$port with the root filesystem read-only and a tmpfs /tmp"
# shellcheck disable=SC2016  # the positional parameters expand in the inner shell
env -i "${image_env[@]}" HOME="$workdir" PASSIVE_LOCATOR_STORE=sqlite:////tmp/sessions.db \
  unshare --mount sh -c 'mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" \
      && mount -t tmpfs -o mode=1777 tmpfs "$1/tmp" \
      && exec chroot --userspec="$2" "$1" /bin/sh -c "cd $3 && exec passive-locator serve --host 127.0.0.1 --port $4"' \
  sh "$mnt" "$uid:$gid" "$workdir" "$port" >"$log" 2>&1 &
server_pid=$!
started=$SECONDS
for _ in $(seq 120); do
  kill -0 "$server_pid" 2>/dev/null || { cat "$log" >&2; fail "server exited (read-only root)"; }
  curl -fsS -o /dev/null "http://127.0.0.1:$port/healthz" 2>/dev/null && break
  sleep 0.5
done
startup_s=$((SECONDS - started))
grep -q 'is read-only: using a copy in /tmp/' "$log" || { cat "$log" >&2; fail "the read-only cache was not copied"; }
grep -q 'kernels ready in .*: 0 compiled' "$log" || { cat "$log" >&2; fail "the start compiled kernels"; }
[ "$startup_s" -le "${SMOKE_MAX_STARTUP_S:-20}" ] || fail "read-only root: the server took ${startup_s} s to answer"
say "read-only root: answered after ${startup_s} s, kernels from the copied cache"
kill -TERM "$server_pid"
for _ in $(seq 40); do kill -0 "$server_pid" 2>/dev/null || break; sleep 0.25; done
server_pid=""
say "PASS"
