#!/usr/bin/env bash
# Idempotent set-up for a fresh Debian machine (root, no screen, registries only):
# system libraries, the .venv with the project and every extra, and the glTF validator.
# A second run with nothing missing only checks and returns in seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

# librecad (dxf2pdf), poppler-utils (pdftoppm) and chromium read the CAD exports back in the tests
SYSTEM_PACKAGES=(libusb-1.0-0 libgl1 libegl1 libgomp1 libosmesa6 libxrender1 libxext6 nodejs npm librecad poppler-utils chromium)
# `papl-map view`: Qt's xcb platform plugin, OpenGL on X (Mesa's llvmpipe when there is no GPU),
# and Xvfb, the X server its tests open the real window on
SYSTEM_PACKAGES+=(libgl1-mesa-dri libglx-mesa0 libxkbcommon-x11-0 libxcb-cursor0 libxcb-icccm4
    libxcb-keysyms1 libxcb-image0 libxcb-render-util0 libxcb-shape0 libxcb-randr0 libxcb-xkb1
    libfontconfig1 libdbus-1-3 xvfb)
# benchmarks/viewer.py also measures Open3D's GUI, which renders through Vulkan (Mesa's lavapipe here)
SYSTEM_PACKAGES+=(libvulkan1 mesa-vulkan-drivers)
missing=()
for pkg in "${SYSTEM_PACKAGES[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
        # npm may come with a nodejs that is not Debian's (e.g. a preinstalled Node.js).
        if [[ "$pkg" == nodejs || "$pkg" == npm ]] && command -v "${pkg/nodejs/node}" >/dev/null; then
            continue
        fi
        missing+=("$pkg")
    fi
done
if ((${#missing[@]})); then
    echo "setup: installing system packages: ${missing[*]}"
    SUDO=""; [[ $(id -u) -ne 0 ]] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PYTHON=${PYTHON:-python3.11}
command -v "$PYTHON" >/dev/null || PYTHON=python3
if [[ ! -x .venv/bin/python ]]; then
    echo "setup: creating .venv with $PYTHON"
    "$PYTHON" -m venv .venv
fi

stamp=.venv/.papl-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [[ ! -f $stamp || "$(cat "$stamp")" != "$want" ]]; then
    echo "setup: installing papl-mapper and its dependencies into .venv"
    .venv/bin/python -m pip install -q --upgrade pip
    # every extra: the core is numpy, scipy, OpenCV, gtsam and PyYAML; rendering (previews, report),
    # USD, DXF, the viewer (the tests open its window under Xvfb) and Ray (the tests run a local cluster)
    # are extras users may leave out; test and dev hold the tests' independent readers and ruff
    .venv/bin/python -m pip install -q -e ".[dev,test,render,usd,dxf,viewer,ray]"
    echo "$want" > "$stamp"
fi

if [[ ! -x .tools/node_modules/.bin/gltf-validator && ! -f .tools/node_modules/gltf-validator/package.json ]]; then
    echo "setup: installing the Khronos glTF validator (npm gltf-validator) into .tools/"
    mkdir -p .tools
    npm install --silent --no-audit --no-fund --prefix .tools gltf-validator@2.0.0-dev.3.10 >/dev/null
fi

# byte-compile the project once: where the environment sets PYTHONDONTWRITEBYTECODE, every run would
# otherwise compile its ~110 modules again (0.1-0.2 s of each run); up-to-date files are skipped
.venv/bin/python -m compileall -q papl_mapper pipelines >/dev/null
