# The companion service in a container, for arm64 and amd64 companion boards (docs/install.md, "Container").
#   docker buildx build --platform linux/arm64,linux/amd64 -t companion-slz .
#   buildah bud --build-arg BASE_IMAGE=localhost/debian-bookworm-python:12 -t companion-slz .
# BASE_IMAGE: any Debian-like image with python3 (3.10+) and its venv module: the official Python
# image by default, or a base made with debootstrap from Debian's own packages
# (scripts/container-base.sh), for builders who take nothing from an image registry.
# Stage 1 builds the wheel from this repository (the model travels inside it as package data);
# stage 2 installs it with its runtime dependencies only (what `companion run` imports) into a
# virtual environment (Debian's own python3 refuses a system-wide pip install) and runs the
# service as an unprivileged user.
ARG BASE_IMAGE=python:3.11-slim-bookworm

FROM ${BASE_IMAGE} AS build
WORKDIR /src
COPY pyproject.toml README.md ./
COPY companion ./companion
COPY sim ./sim
RUN python3 -m venv /opt/build && /opt/build/bin/pip wheel --no-cache-dir --no-deps --wheel-dir /wheels .

FROM ${BASE_IMAGE}
# No compiler and no apt packages: every runtime dependency ships manylinux wheels for both
# architectures (opencv-python-headless needs no X or GL libraries).
COPY --from=build /wheels /wheels
RUN python3 -m venv /opt/companion && /opt/companion/bin/pip install --no-cache-dir /wheels/*.whl \
    && rm -rf /wheels \
    && useradd --system --home-dir /var/lib/companion --create-home --shell /usr/sbin/nologin \
               --groups dialout,video companion \
    && install -d -m 0755 /etc/companion
ENV PATH=/opt/companion/bin:$PATH
# The documented example: every key at its default (the simulator's); mount your own over it.
COPY companion.example.toml /etc/companion/companion.toml
USER companion
WORKDIR /var/lib/companion
VOLUME ["/var/lib/companion"]
# SIGTERM (docker stop) hands control back to the autopilot before the service exits.
STOPSIGNAL SIGTERM
ENTRYPOINT ["companion", "run", "--config", "/etc/companion/companion.toml"]
