#!/usr/bin/env bash
# Installs what pbrl needs beyond the Rust toolchain: a TrueType font for the pictures
# (`pbrl env render`). Safe to run again; does nothing when everything is there.
set -euo pipefail
font=/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf
if [ ! -f "$font" ] && [ -z "${PBRL_FONT:-}" ]; then
    if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
        apt-get update -qq && apt-get install -y -qq fonts-dejavu-core >/dev/null
    else
        echo "pbrl: no font at $font; install fonts-dejavu-core or set PBRL_FONT to a .ttf file" >&2
    fi
fi
command -v cargo >/dev/null 2>&1 || { echo "pbrl: cargo not found; install Rust (rustup)" >&2; exit 1; }
