# syntax=docker/dockerfile:1
FROM python:3.11-slim AS build
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1
WORKDIR /src
RUN python -m venv /opt/venv
COPY pyproject.toml README.md ./
# Dependencies first (cached while only the source changes).
RUN /opt/venv/bin/pip install "numpy>=1.26" "scipy>=1.11" "pymap3d>=3.1" "fastapi>=0.110" "uvicorn[standard]>=0.29" \
        "pydantic>=2.6" "pydantic-settings>=2.2" "orjson>=3.9" "httpx>=0.27" "redis>=5.0"
COPY core ./core
COPY service ./service
RUN /opt/venv/bin/pip install --no-deps .

FROM python:3.11-slim
RUN useradd --system --uid 10001 --home /app locator && mkdir -p /app/var && chown locator /app/var
COPY --from=build /opt/venv /opt/venv
WORKDIR /app
USER locator
ENV PATH=/opt/venv/bin:$PATH PASSIVE_LOCATOR_STORE=sqlite:////app/var/sessions.db
EXPOSE 8080
HEALTHCHECK --interval=30s --timeout=3s CMD python -c "import urllib.request,sys; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8080/healthz').status == 200 else 1)"
CMD ["passive-locator", "serve", "--host", "0.0.0.0", "--port", "8080"]
