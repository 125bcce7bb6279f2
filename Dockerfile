# Headless motiond: docker build -t motiond . && docker run -p 127.0.0.1:2323:2323 -p 127.0.0.1:8080:8080 -v motiond-data:/data motiond
# It listens on every interface inside the container, so it never runs without a token: the first
# start makes one in /data/.token and prints it (docker logs); or pass -e MOTIOND_TOKEN=...
# Reached by name from the LAN: -e MOTIOND_ALLOWED_HOSTS=nas.local (docs/docker.md).
# The build stage compiles the Klipper backend's step core and the parser's words (gcc; the image's
# Python has its headers) into a virtual environment the image copies: no compiler, pip or setuptools in the image.
# podman: build with --format docker (the OCI format has no HEALTHCHECK).
FROM python:3.11-slim AS build

# unpinned (DL3008): the versions are the base image's Debian release's
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/*
RUN python -m venv /opt/motiond
WORKDIR /src
COPY pyproject.toml setup.py README.md ./
COPY server ./server
COPY modules ./modules
COPY web ./web
# a non-editable install: the package and its core live in the environment (-I: not /src);
# then the installers go: the image runs motiond, it installs nothing
RUN /opt/motiond/bin/pip install --no-cache-dir "./[mqtt,fast]" \
    && /opt/motiond/bin/python -I -c "import server.backends.klipper._stepcore, server.gcode._words" \
    && /opt/motiond/bin/python -m pip uninstall --yes --quiet pip setuptools wheel

FROM python:3.11-slim

# the base image's own pip, setuptools and wheel (motiond's environment has none)
RUN rm -rf /usr/local/lib/python3.*/site-packages/pip /usr/local/lib/python3.*/site-packages/pip-* \
        /usr/local/lib/python3.*/site-packages/setuptools /usr/local/lib/python3.*/site-packages/setuptools-* \
        /usr/local/lib/python3.*/site-packages/_distutils_hack /usr/local/lib/python3.*/site-packages/distutils-precedence.pth \
        /usr/local/lib/python3.*/site-packages/wheel /usr/local/lib/python3.*/site-packages/wheel-* \
        /usr/local/bin/pip /usr/local/bin/pip3* /usr/local/bin/wheel \
    && useradd --create-home --uid 10001 motiond \
    && mkdir -p /data \
    && chown motiond:motiond /data

COPY --from=build /opt/motiond /opt/motiond
ENV PATH=/opt/motiond/bin:$PATH
WORKDIR /app

USER 10001
VOLUME ["/data"]
# Optional: mount a config and point MOTIOND_CONFIG at it, e.g. -e MOTIOND_CONFIG=/data/motiond.toml
# The data folder: job files in /data/jobs, the default machine's settings in /data/settings.toml
ENV MOTIOND_DATA_DIR=/data
EXPOSE 2323 8080
# GET /health on the HTTP port the config or $MOTIOND_HTTP_PORT gives: "ok" while the server
# runs (no session, no log line); light (tomllib, no machine built), so it can run every 10 s
HEALTHCHECK --interval=10s --timeout=3s --start-period=20s --retries=3 \
    CMD ["python", "-m", "server.health"]
CMD ["motiond", "--host", "0.0.0.0"]
