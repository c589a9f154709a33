#!/usr/bin/env bash
# Sets up jaxden in ./.venv: Debian's libLLVM 19 for Mitsuba's fast CPU variant (where apt
# works), then the package and its test dependencies. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")"
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  if ! ldconfig -p 2>/dev/null | grep -q 'libLLVM.so.19\|libLLVM-19'; then
    echo "setup: installing libllvm19 for Mitsuba's llvm_ad_rgb variant"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null) \
      || echo "setup: could not install libllvm19; rendering will fall back to scalar_rgb"
  fi
else
  echo "setup: not root or no apt-get; skipping libllvm19 (rendering may fall back to scalar_rgb)"
fi
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip 2>&1 | grep -v '^WARNING: Location' || true
.venv/bin/python -m pip install -q --disable-pip-version-check -e '.[test]' 2>&1 | grep -v '^WARNING: Location' || true
.venv/bin/python -c "import jaxden, jax, mitsuba, OpenEXR" || { echo "setup: install failed"; exit 1; }
