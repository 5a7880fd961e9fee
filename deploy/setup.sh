#!/usr/bin/env bash
# Installs what pbrl needs beyond the Rust toolchain: a TrueType font for the pictures
# (`pbrl env render`), and headless Chromium with its WebDriver for the labelling page's
# browser test (`tests/labelling.rs`). Safe to run again; does nothing when everything is
# there.
set -euo pipefail
font=/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf
need=()
if [ ! -f "$font" ] && [ -z "${PBRL_FONT:-}" ]; then
    need+=(fonts-dejavu-core)
fi
if [ -z "${PBRL_SKIP_BROWSER:-}" ]; then
    command -v chromium >/dev/null 2>&1 || need+=(chromium)
    command -v chromedriver >/dev/null 2>&1 || need+=(chromium-driver)
fi
if [ ${#need[@]} -gt 0 ]; then
    if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
        apt-get update -qq && apt-get install -y -qq "${need[@]}" >/dev/null
    else
        echo "pbrl: please install ${need[*]} (Debian package names); PBRL_FONT names another .ttf, PBRL_SKIP_BROWSER=1 skips the browser test" >&2
    fi
fi
command -v cargo >/dev/null 2>&1 || { echo "pbrl: cargo not found; install Rust (rustup)" >&2; exit 1; }
