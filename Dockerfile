# Base: the official python:3.11-slim (Debian bookworm). Only `python -m venv` and /opt/venv/bin/* are
# used, never /usr/local/bin/python or a global pip, so a Debian-python stand-in base builds it too
# (scripts/container_smoke.sh says how to make one without registry access).
# podman/buildah: build with `--format docker`; the OCI default format drops HEALTHCHECK.
FROM python:3.11-slim AS build
# numba keeps its compiled kernels here; filled below, so a container starts warm when it runs on the
# build's CPU model (and compiles at start otherwise, saying so in its log). Not under /tmp or any other
# path a deployment mounts a volume on: a volume there would hide the cache and every start would compile.
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1 NUMBA_CACHE_DIR=/opt/numba-cache
WORKDIR /src
RUN python -m venv /opt/venv
# Dependencies first, read from pyproject.toml itself (no second list to drift from it) and pinned to the
# tested versions by constraints.txt (`make constraints`): this layer is rebuilt only when those two change,
# not when the source or the README does.
# EXTRAS: optional-dependency groups to add, comma-separated: `--build-arg EXTRAS=distributed` gives the
# image the Dask scheduler and workers of deploy/ run (and the API with PASSIVE_LOCATOR_DASK_SCHEDULER).
ARG EXTRAS=""
COPY pyproject.toml constraints.txt ./
RUN EXTRAS="$EXTRAS" /opt/venv/bin/python -c "import os, tomllib; p = tomllib.load(open('pyproject.toml', 'rb'))['project']; print(*p['dependencies'], *(r for e in os.environ['EXTRAS'].split(',') if e for r in p['optional-dependencies'][e]), sep='\n')" \
        > /tmp/requirements.txt \
    && /opt/venv/bin/pip install -c constraints.txt -r /tmp/requirements.txt
COPY README.md ./
COPY core ./core
COPY service ./service
# The kernels are compiled from the installed package, not from /src: numba keys its cache by the source
# file's path, so a cache filled from /src/core is never read by the runtime (which imports site-packages)
# and every container start would compile them all again.
# The runtime needs no installer: pip and setuptools leave the venv once it is complete and checked; nor
# numpy's and scipy's own test suites (about 50 MB).
RUN /opt/venv/bin/pip install --no-deps . && /opt/venv/bin/pip check \
    && (cd / && /opt/venv/bin/python -c "from service.fixes.pipeline import compile_kernels; compile_kernels()") \
    && find /opt/venv/lib/python3*/site-packages/numpy /opt/venv/lib/python3*/site-packages/scipy \
        -type d -name tests -prune -exec rm -rf {} + \
    && (/opt/venv/bin/pip uninstall --yes --quiet setuptools wheel || true) \
    && /opt/venv/bin/python -m pip uninstall --yes --quiet pip \
    && ! /opt/venv/bin/python -c "import pip" 2>/dev/null

FROM python:3.11-slim
# No installer in the runtime either: the base's own pip, setuptools and the wheels ensurepip/venv would
# install (the official image has them under /usr/local, Debian's python3-venv under /usr/share).
RUN (python -m pip uninstall --yes --quiet pip setuptools wheel 2>/dev/null || true) \
    && rm -rf /usr/local/lib/python3*/ensurepip /usr/share/python-wheels /usr/local/bin/pip*
# Fixed numeric ids: USER is numeric so a runtime can verify non-root (Kubernetes runAsNonRoot), and the
# store directory's owner matches the user a volume or `--user 10001:10001` brings.
RUN groupadd --system --gid 10001 locator \
    && useradd --system --uid 10001 --gid 10001 --home-dir /app --no-create-home --shell /usr/sbin/nologin locator \
    && mkdir -p /app/var && chown 10001:10001 /app/var
COPY --from=build /opt/venv /opt/venv
# Writable by the service's user, so a plain `run` adds to it; under a read-only root filesystem (the
# manifests in deploy/) `passive-locator serve` copies it to a fresh temporary directory first, since numba
# ignores a cache directory it cannot write (service/ops/kernel_cache.py).
COPY --from=build --chown=10001:10001 /opt/numba-cache /opt/numba-cache
WORKDIR /app
USER 10001:10001
ENV PATH=/opt/venv/bin:$PATH PASSIVE_LOCATOR_STORE=sqlite:////app/var/sessions.db NUMBA_CACHE_DIR=/opt/numba-cache
VOLUME ["/app/var"]
EXPOSE 8080
# The start period covers a start that compiles the kernels (a CPU model other than the build's): README.
HEALTHCHECK --interval=30s --timeout=3s --start-period=300s CMD python -c "import urllib.request,sys; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8080/healthz').status == 200 else 1)"
CMD ["passive-locator", "serve", "--host", "0.0.0.0", "--port", "8080"]
