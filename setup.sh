#!/usr/bin/env bash
# Sets up jaxden in ./.venv: Debian's libLLVM 19 for Mitsuba's fast CPU variant (where apt
# works), then the package and its test dependencies. Safe to run again; prints one summary line
# (and a line per problem).
set -euo pipefail
cd "$(dirname "$0")"
log=$(mktemp); trap 'rm -f "$log"' EXIT
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  if ! ldconfig -p 2>/dev/null | grep -q 'libLLVM.so.19\|libLLVM-19'; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) >"$log" 2>&1 \
      || echo "setup: could not install libllvm19 (rendering will fall back to scalar_rgb): $(tail -1 "$log")"
  fi
else
  echo "setup: not root or no apt-get; skipping libllvm19 (rendering may fall back to scalar_rgb)"
fi
[ -x .venv/bin/python ] || python3 -m venv .venv
pip=(.venv/bin/python -m pip install -q --disable-pip-version-check)
if ! { "${pip[@]}" --upgrade pip && "${pip[@]}" -e '.[test,ray]'; } >"$log" 2>&1; then
  grep -v '^WARNING: Location' "$log" | tail -20; echo "setup: pip install failed"; exit 1
fi
.venv/bin/python - <<'PY' || { echo "setup: install failed (see above)"; exit 1; }
import importlib.metadata as m
import jaxden, jax, mitsuba, OpenEXR  # noqa: F401  (all importable)
from jaxden.render.variant import choose_variant
names = ("jax", "flax", "mitsuba", "pyoidn")
versions = ", ".join(f"{n} {m.version(n)}" for n in names)
print(f"setup: jaxden {jaxden.__version__} ready in .venv ({versions}; Mitsuba variant "
      f"{choose_variant()})")
PY
