# The companion service in a container, for arm64 and amd64 companion boards (docs/install.md, "Docker").
#   docker buildx build --platform linux/arm64,linux/amd64 -t companion-slz .
# Stage 1 builds the wheel from this repository (the model travels inside it as package data);
# stage 2 installs it with its runtime dependencies only (what `companion run` imports) into a
# slim Python and runs the service as an unprivileged user.
ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS build
WORKDIR /src
COPY pyproject.toml README.md ./
COPY companion ./companion
COPY sim ./sim
RUN pip wheel --no-cache-dir --no-deps --wheel-dir /wheels .

FROM ${PYTHON_IMAGE}
# No compiler and no apt packages: every runtime dependency ships manylinux wheels for both
# architectures (opencv-python-headless needs no X or GL libraries).
COPY --from=build /wheels /wheels
RUN pip install --no-cache-dir /wheels/*.whl && rm -rf /wheels \
    && useradd --system --home-dir /var/lib/companion --create-home --shell /usr/sbin/nologin \
               --groups dialout,video companion \
    && install -d -m 0755 /etc/companion
# The documented example: every key at its default (the simulator's); mount your own over it.
COPY companion.example.toml /etc/companion/companion.toml
USER companion
WORKDIR /var/lib/companion
VOLUME ["/var/lib/companion"]
# SIGTERM (docker stop) hands control back to the autopilot before the service exits.
STOPSIGNAL SIGTERM
ENTRYPOINT ["companion", "run", "--config", "/etc/companion/companion.toml"]
