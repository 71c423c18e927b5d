#!/usr/bin/env bash
# Installs asp-dist with the CPU build of PyTorch. Installing torch==2.13.0 first keeps pip
# from pulling a CUDA build (several GB); the project itself accepts any torch>=2.3.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
"$PY" -m pip install --quiet --disable-pip-version-check "torch==2.13.0"
"$PY" -m pip install --quiet --disable-pip-version-check -e ".[test]"
# The worked plugin of docs/extending.md, installed as a user installs one: the registry-wide tests run on it.
"$PY" -m pip install --quiet --disable-pip-version-check -e examples/referential-game

# tests/test_report_html.py opens report.html in Debian's headless Chromium (it skips without one).
# As root with apt-get, install it when missing; a failure only warns, the Python install stands.
if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1 \
    && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  apt_install() { DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null 2>&1; }
  if ! { apt_install || { apt-get update -qq >/dev/null 2>&1 && apt_install; }; }; then
    echo "install.sh: warning: apt-get could not install chromium; the report.html browser check will skip" >&2
  fi
fi
