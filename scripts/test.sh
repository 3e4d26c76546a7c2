#!/usr/bin/env bash
# The README's test command: install test dependencies, run the test suite,
# then run the SocketCAN (vcan) suite inside a user-mode Linux kernel.
#
#   ./scripts/test.sh            # everything
#   SKIP_VCAN=1 ./scripts/test.sh   # skip the user-mode-linux vcan suite
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

"$PY" -m pip install -q -e '.[test]'

# System packages: user-mode-linux provides a kernel with vcan for the CAN suite.
if [ "${SKIP_VCAN:-0}" != 1 ] && [ ! -x /usr/bin/linux.uml ] && command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -q --no-install-recommends user-mode-linux iproute2 kmod >/dev/null 2>&1 ||
        { apt-get update -q >/dev/null && apt-get install -y -q --no-install-recommends user-mode-linux iproute2 kmod >/dev/null; }
fi

"$PY" -m ruff check .

# The API reference (docs/, Sphinx autodoc): docstring or cross-reference problems fail the build.
"$PY" -m sphinx -W --keep-going -q -b html docs build/docs

# Main suite (vcan-marked tests are skipped here: this kernel has no CAN).
set +e
"$PY" -m pytest -m "not vcan" "$@"
rc=$?
set -e
[ $rc -eq 0 ] || exit $rc

if [ "${SKIP_VCAN:-0}" != 1 ]; then
    echo "--- vcan suite (real SocketCAN inside user-mode Linux)"
    PYBIN=$("$PY" -c 'import sys; print(sys.executable)')
    bash scripts/run-in-vcan.sh "$PYBIN" -m pytest -m vcan -p no:cacheprovider "$@"
fi
