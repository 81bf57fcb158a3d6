#!/usr/bin/env bash
# System prerequisites of the test suite, installed once by `make test`:
#   - Debian's chromium (/usr/bin/chromium), driven by Playwright in the monitor's browser test;
#   - node-opcua (npm), the independent OPC UA client of the interoperability tests,
#     into $NODE_OPCUA_DIR (default out/.node_opcua).
# chromium needs root and Debian's package repositories; node-opcua needs node and npm.
set -euo pipefail
NODE_OPCUA_VERSION="${NODE_OPCUA_VERSION:-2.186.4}"
NODE_OPCUA_DIR="${NODE_OPCUA_DIR:-out/.node_opcua}"

# two checkouts testing at once on one machine would both run apt-get, and the second
# would fail on apt's lock: the installs here take turns (up to 15 min of waiting)
exec 9>"${TMPDIR:-/tmp}/minetwin-test-prereqs.lock"
if ! flock -w 900 9; then
    echo "test prerequisites: another install held ${TMPDIR:-/tmp}/minetwin-test-prereqs.lock for 15 min" >&2
    exit 1
fi

if [ ! -x /usr/bin/chromium ]; then
    if [ "$(id -u)" -ne 0 ] || ! command -v apt-get >/dev/null; then
        echo "test prerequisites: /usr/bin/chromium is missing; install Debian's 'chromium' package (needs root)" >&2
        exit 1
    fi
    echo "test prerequisites: installing Debian's chromium (apt-get)" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get -o DPkg::Lock::Timeout=600 update -qq
    apt-get -o DPkg::Lock::Timeout=600 install -y -qq chromium >/dev/null
fi

marker="$NODE_OPCUA_DIR/node_modules/node-opcua/package.json"
if [ ! -f "$marker" ] || ! grep -q "\"version\": \"$NODE_OPCUA_VERSION\"" "$marker"; then
    if ! command -v npm >/dev/null || ! command -v node >/dev/null; then
        echo "test prerequisites: node and npm are needed for node-opcua; install Debian's 'nodejs' and 'npm'" >&2
        exit 1
    fi
    echo "test prerequisites: installing node-opcua@$NODE_OPCUA_VERSION into $NODE_OPCUA_DIR (npm)" >&2
    mkdir -p "$NODE_OPCUA_DIR"
    [ -f "$NODE_OPCUA_DIR/package.json" ] || echo '{"name": "minetwin-interop", "private": true}' > "$NODE_OPCUA_DIR/package.json"
    (cd "$NODE_OPCUA_DIR" && npm install --no-audit --no-fund --loglevel=error "node-opcua@$NODE_OPCUA_VERSION" >/dev/null)
fi
echo "test prerequisites: chromium $(/usr/bin/chromium --version 2>/dev/null | awk '{print $2}'), node-opcua $NODE_OPCUA_VERSION" >&2
