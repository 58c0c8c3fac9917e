#!/usr/bin/env bash
# Set up, then run the whole test suite (extra arguments go to pytest).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
. "$root/scripts/setup.sh"
cd "$root"
# Optional: a virtual X server, so the guided calibration's Tk windows are tested too (the tests
# skip them without one).  Installed only where we are root with apt-get; never required.
if ! command -v Xvfb >/dev/null 2>&1 && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  printf '[test] installing xvfb (optional, for the Tk window tests) with apt-get\n' >&2
  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq xvfb; } >/dev/null 2>&1 ||
    printf '[test] xvfb not installed; the Tk window tests will skip\n' >&2
fi
exec python -m pytest "$@"
