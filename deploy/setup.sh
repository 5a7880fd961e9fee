#!/usr/bin/env bash
# Installs what the tests and the pictures need beyond the Rust toolchain (training needs
# none of it): a TrueType font for the pictures (`pbrl env render`), headless Chromium with
# its WebDriver for the browser tests (`tests/labelling.rs`, `tests/policy.rs`), python3
# (`deploy/label.py` and the HTTPS tests), openssl (`deploy/certs.sh`), curl and iproute2
# (the deployment tests: `ip netns`), tmux (the terminal test), and the stock Zenoh router
# `zenohd` (below). Safe to run again; does nothing when everything is there.
set -euo pipefail
font=/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf
need=()
if [ ! -f "$font" ] && [ -z "${PBRL_FONT:-}" ]; then
    need+=(fonts-dejavu-core)
fi
for tool in python3:python3 openssl:openssl curl:curl ip:iproute2 tmux:tmux; do
    command -v "${tool%%:*}" >/dev/null 2>&1 || need+=("${tool#*:}")
done
if [ -z "${PBRL_SKIP_BROWSER:-}" ]; then
    command -v chromium >/dev/null 2>&1 || need+=(chromium)
    command -v chromedriver >/dev/null 2>&1 || need+=(chromium-driver)
fi
if [ ${#need[@]} -gt 0 ]; then
    if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
        apt-get update -qq && apt-get install -y -qq "${need[@]}" >/dev/null
    else
        echo "pbrl: please install ${need[*]} (Debian package names); PBRL_FONT names another .ttf, PBRL_SKIP_BROWSER=1 skips the browser tests" >&2
        exit 1
    fi
fi
command -v cargo >/dev/null 2>&1 || { echo "pbrl: cargo not found; install Rust (rustup)" >&2; exit 1; }
# The stock Zenoh router, zenohd, at the zenoh version of Cargo.lock with the TCP and TLS
# transports pbrl uses: the multi-host, TLS and fault tests run it, and so does a
# deployment across machines (docs/deploy.md). Built once (a few minutes) into
# $CARGO_HOME/bin; PBRL_SKIP_ZENOHD=1 skips it (those tests then fail, saying why).
want=$(awk '/^name = "zenoh"$/ { getline; gsub(/[^0-9.]/, ""); print; exit }' "$(dirname "$0")/../Cargo.lock")
zenohd="${CARGO_HOME:-$HOME/.cargo}/bin/zenohd"
have=$("$zenohd" --version 2>/dev/null | grep -oE '[0-9]+\.[0-9]+\.[0-9]+' | head -1 || true)
if [ -z "${PBRL_SKIP_ZENOHD:-}" ] && [ "$have" != "$want" ]; then
    echo "pbrl: building zenohd $want into $(dirname "$zenohd") (once, a few minutes)" >&2
    cargo install zenohd --version "=$want" --locked --quiet --no-default-features \
        --features zenoh/transport_tcp,zenoh/transport_tls
fi
