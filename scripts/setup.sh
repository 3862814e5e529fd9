#!/usr/bin/env bash
# One command to set everything up: the Python environment (.venv, the package and its dependencies) and, where
# Debian's apt is at hand, the independent DICOM readers the tests check our DICOM files with (dicom3tools'
# dciodvfy, plastimatch). Run from the repository root: bash scripts/setup.sh
set -euo pipefail
cd "$(dirname "$0")/.."
if command -v dciodvfy >/dev/null && command -v plastimatch >/dev/null; then
    :
elif command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq dicom3tools plastimatch >/dev/null
elif command -v apt-get >/dev/null && command -v sudo >/dev/null; then
    sudo apt-get update -qq
    sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq dicom3tools plastimatch >/dev/null
else
    echo "setup: dicom3tools and plastimatch not installed (no apt-get as root here); the tests that check DICOM files" \
         "with these independent readers will skip, saying so" >&2
fi
python3 -m venv .venv
.venv/bin/pip install -q -e ".[test]"
echo "setup: done (.venv; dciodvfy: $(command -v dciodvfy || echo absent); plastimatch: $(command -v plastimatch || echo absent))"
