#!/usr/bin/env bash
# Build the companion's container image from Debian's own packages and check that it runs.
#
#   sudo scripts/container-build.sh [ARCH]        # ARCH: amd64 (default: this machine's) or arm64
#
# 1. debootstrap makes a minimal Debian 12 (bookworm) root with python3 and its venv module, and
#    podman imports it as the base image localhost/debian-bookworm-python:12-ARCH: no image is
#    pulled from any registry.
# 2. buildah builds the repository's Dockerfile on that base (BASE_IMAGE build argument); the
#    image is localhost/companion-slz:VERSION-ARCH.
# 3. Inside the image: `companion --version`, and (natively only, see below) a two-frame replay of
#    synthetic crowd frames drawn inside the image by the package itself; its summary must count 2.
#
# Needs: debootstrap, buildah, podman (Debian packages), root, and for arm64 on an amd64 host
# qemu-user-static with binfmt support. MIRROR (default Debian's deb.debian.org redirector) picks
# the Debian mirror. Behind a TLS-intercepting proxy the build mounts the host's CA bundle
# (CA_BUNDLE, default /etc/ssl/certs/ca-certificates.crt) for pip; nothing of it stays in the image.
# Steps run with buildah's chroot isolation, which works where podman's OCI runtime may not be
# allowed to set resource limits (containers inside containers).
set -euo pipefail

ARCH="${1:-$(dpkg --print-architecture)}"
MIRROR="${MIRROR:-http://deb.debian.org/debian}"
CA_BUNDLE="${CA_BUNDLE:-/etc/ssl/certs/ca-certificates.crt}"
WORK="${WORK:-/var/tmp/companion-container}"
REPO="$(cd "$(dirname "$0")/.." && pwd)"
VERSION="$(sed -n 's/^__version__ = "\(.*\)"/\1/p' "$REPO/companion/__init__.py" | head -1)"
BASE="localhost/debian-bookworm-python:12-$ARCH"
IMAGE="localhost/companion-slz:$VERSION-$ARCH"

for tool in debootstrap buildah podman; do
    command -v "$tool" >/dev/null || { echo "container-build: $tool is missing (apt-get install $tool)" >&2; exit 2; }
done

if ! podman image exists "$BASE"; then
    rootfs="$WORK/rootfs-$ARCH"
    rm -rf "$rootfs" && mkdir -p "$WORK"
    echo "== debootstrap bookworm ($ARCH) into $rootfs"
    debootstrap --arch="$ARCH" --variant=minbase --include=python3,python3-venv,ca-certificates \
        bookworm "$rootfs" "$MIRROR" >"$WORK/debootstrap-$ARCH.log"
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
    tar -C "$rootfs" -c . | podman import --arch "$ARCH" - "$BASE" >/dev/null
    rm -rf "$rootfs"
fi
echo "== base $BASE"

mounts=()
[ -f "$CA_BUNDLE" ] && mounts=(--volume "$CA_BUNDLE:/etc/ssl/certs/ca-certificates.crt:ro")
echo "== buildah bud -> $IMAGE"
buildah bud --isolation chroot --network host --arch "$ARCH" "${mounts[@]}" \
    --build-arg BASE_IMAGE="$BASE" -t "$IMAGE" "$REPO"

echo "== checks inside $IMAGE"
ctr="$(buildah from "$IMAGE")"
trap 'buildah rm "$ctr" >/dev/null' EXIT
buildah run --isolation chroot "$ctr" -- companion --version
if [ "$ARCH" != "$(dpkg --print-architecture)" ]; then
    # Measured 2026-12-06 with Debian 12's qemu-user-static 7.2: onnxruntime 1.32's arm64 wheel
    # dies of SIGSEGV on import under emulation (numpy, OpenCV and SciPy import), so the replay is
    # checked on a machine of the image's own architecture: run this script there.
    echo "== replay check skipped: $ARCH is emulated here (onnxruntime crashes under qemu-user)"
    exit 0
fi
buildah run --isolation chroot "$ctr" -- sh -ec '
    cd /tmp && mkdir -p frames
    python3 -c "
import cv2
from companion import synthetic
for i in range(2):
    scene = synthetic.crowd_scene(seed=i)
    cv2.imwrite(f\"frames/{i:03d}.png\", synthetic.render(scene, seed=i))
"
    companion replay frames --nadir --gsd 0.05 --no-progress --summary-json summary.json >/dev/null
    python3 -c "
import json
s = json.load(open(\"summary.json\"))
n = s[\"frames\"]
assert n == 2, s
print(\"two-frame replay inside the image:\", n, \"frames\")
"'
podman image inspect "$IMAGE" --format '{{.Architecture}} {{.Size}} bytes: {{index .RepoTags 0}}'
