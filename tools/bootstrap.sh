#!/usr/bin/env bash
# Idempotent set-up of the project venv on a fresh Debian 12 machine: python3 venv from the pinned
# lock, then the rosidl export-path fix. Re-runs in well under a second when the lock is unchanged.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv="$root/.venv"
lock="$root/requirements.lock"
stamp="$venv/.lock.sha256"
want=$(sha256sum "$lock" | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x "$venv/bin/python" ]; then
  exit 0
fi
python=${PYTHON:-python3}
if ! "$python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
  echo "bootstrap: the ROS 2 Jazzy wheels need CPython 3.11; set PYTHON=/path/to/python3.11" >&2
  exit 1
fi
if ! command -v cmake >/dev/null || ! command -v cc >/dev/null || ! command -v c++ >/dev/null; then
  echo "bootstrap: installing cmake and a C/C++ compiler (Debian packages)"
  apt-get update -qq && apt-get install -y -qq cmake g++ make >/dev/null
fi
echo "bootstrap: creating $venv from requirements.lock"
[ -x "$venv/bin/python" ] || "$python" -m venv "$venv"
"$venv/bin/python" -m pip install -q --disable-pip-version-check -r "$lock"
"$venv/bin/python" "$root/tools/fix_rosidl_paths.py"
echo "$want" > "$stamp"
