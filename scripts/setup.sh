#!/usr/bin/env bash
# Set up a fresh machine for gbscan/gbcal: a virtualenv in .venv with the project and its
# dependencies, plus the one system library open3d's Linux wheel links (libusb-1.0).
# Idempotent and quick when nothing changed.  Source it (". scripts/setup.sh") to keep the
# venv active, or run it.  GB_PYTHON=/path/to/python3.11+ chooses the interpreter.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
say() { printf '[setup] %s\n' "$*" >&2; }

pick_python() {
  for cand in "${GB_PYTHON:-}" python3 python3.13 python3.12 python3.11 python; do
    [ -n "$cand" ] || continue
    command -v "$cand" >/dev/null 2>&1 || continue
    if "$cand" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' 2>/dev/null; then
      echo "$cand"; return 0
    fi
  done
  return 1
}

# 1. System library for open3d (Linux): libusb-1.0.so.0.
if [ "$(uname -s)" = "Linux" ] && ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    say "installing libusb-1.0-0 (needed by open3d) with apt-get"
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    say "open3d needs the system library libusb-1.0; install it once with:"
    say "    sudo apt-get install libusb-1.0-0      (Debian/Ubuntu; other distros: libusb1)"
    exit 1
  fi
fi

# 2. Virtualenv with the project (editable) and the test extras.
if [ ! -x "$venv/bin/python" ]; then
  py="$(pick_python)" || { say "need Python 3.11 or newer (set GB_PYTHON=/path/to/python3.11)"; exit 1; }
  say "creating $venv with $("$py" --version 2>&1)"
  "$py" -m venv "$venv"
fi
stamp="$venv/.gbscan-installed"
# the stamp covers pyproject.toml and this checkout's path: a venv copied from (or installed
# editable by) another checkout is reinstalled here, so `gbscan` never runs someone else's code
want="$({ cat "$root/pyproject.toml"; echo "$root"; } | sha256sum | cut -c1-16)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  say "installing gbscan and its dependencies into .venv (first time: a few minutes)"
  log="$venv/pip-install.log"
  if ! { "$venv/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip &&
         "$venv/bin/python" -m pip install -q --disable-pip-version-check -e "$root[test,batch]"; } >"$log" 2>&1 ||
     ! "$venv/bin/python" -c "import numpy, scipy, cv2, open3d, yaml, numba, gbscan, gbcal" >>"$log" 2>&1; then
    tail -n 30 "$log" >&2
    say "installation failed; the full log is $log"
    exit 1
  fi
  echo "$want" > "$stamp"
fi
# 3. Optional: tkinter for the guided calibration's windows (in the stdlib, but Debian/Ubuntu's
#    system Python ships it as the separate package python3-tk).  Never fatal.
if ! "$venv/bin/python" -c "import tkinter" >/dev/null 2>&1; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1 && [ "$("$venv/bin/python" -c 'import sys; print(sys.base_prefix)')" = "/usr" ]; then
    say "installing python3-tk (the guided calibration's windows) with apt-get"
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-tk; } >/dev/null 2>&1 ||
      say "python3-tk not installed; scripts/guided_calibration.py will need it at a rig (--simulate works without)"
  else
    say "note: this Python has no tkinter; scripts/guided_calibration.py needs it at a rig (Debian/Ubuntu: sudo apt-get install python3-tk)"
  fi
fi
# 4. Byte-compile the project's own modules (an editable install leaves them as sources; where
#    PYTHONDONTWRITEBYTECODE is set, as in many containers, every command would compile them
#    afresh: ~0.1 s of each `gbscan scan`).  Up-to-date files are skipped: quick.
"$venv/bin/python" -m compileall -q "$root/gbscan" "$root/gbcal" >/dev/null 2>&1 || true
export PATH="$venv/bin:$PATH"
export VIRTUAL_ENV="$venv"
