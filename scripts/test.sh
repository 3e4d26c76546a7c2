#!/usr/bin/env bash
# The README's test command: install test dependencies, run the test suite,
# then run the SocketCAN (vcan) suite inside a user-mode Linux kernel.
#
#   ./scripts/test.sh            # everything
#   SKIP_VCAN=1 ./scripts/test.sh   # skip the user-mode-linux vcan suite
#   TEST_WORKERS=0 ./scripts/test.sh   # the main suite in one process (default: 2 parallel workers)
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
# iproute2 (ip netns, tc netem) for the network-namespace tests of the ROS 2 face (tests/test_ros2_netns.py)
if { ! command -v ip >/dev/null || ! command -v tc >/dev/null; } && command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -q --no-install-recommends iproute2 >/dev/null 2>&1 ||
        { apt-get update -q >/dev/null && apt-get install -y -q --no-install-recommends iproute2 >/dev/null; }
fi

# System packages: offscreen OpenGL (Mesa's EGL with the llvmpipe software rasterizer, OSMesa as a
# fallback) so `agentsdk run --video` renders with MuJoCo on a machine without a display.
if ! ldconfig -p 2>/dev/null | grep -q -E 'libEGL_mesa\.so|libOSMesa\.so' && command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    export DEBIAN_FRONTEND=noninteractive
    GL_PKGS="libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6"
    apt-get install -y -q --no-install-recommends $GL_PKGS >/dev/null 2>&1 ||
        { apt-get update -q >/dev/null && apt-get install -y -q --no-install-recommends $GL_PKGS >/dev/null; }
fi

# System packages: the independent ROS 2 peers of the interop tests (tests/test_ros2_interop.py) are
# built from Eclipse Cyclone DDS C (idlc) and eProsima Fast DDS (fastddsgen, C++), Debian's packages.
if { ! command -v idlc >/dev/null || ! command -v fastddsgen >/dev/null || ! command -v g++ >/dev/null; } &&
    command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    export DEBIAN_FRONTEND=noninteractive
    ROS2_PEER_PKGS="cyclonedds-dev cyclonedds-tools libfastrtps-dev fastddsgen fastdds-tools gcc g++"
    apt-get install -y -q --no-install-recommends $ROS2_PEER_PKGS >/dev/null 2>&1 ||
        { apt-get update -q >/dev/null && apt-get install -y -q --no-install-recommends $ROS2_PEER_PKGS >/dev/null; }
fi

# System packages: a headless Chromium and its WebDriver for the web view's browser test (selenium drives them).
if { ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; } && command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -q --no-install-recommends chromium chromium-driver >/dev/null 2>&1 ||
        { apt-get update -q >/dev/null && apt-get install -y -q --no-install-recommends chromium chromium-driver >/dev/null; }
fi

# Every suite runs even when an earlier one fails; the failures are listed at the end and the
# script exits non-zero if there was any (one failing lint must not hide a failing test run).
FAILED=()
suite() {  # suite NAME CMD...: run one suite, remember it if it fails
    local name=$1
    shift
    echo "--- $name"
    if "$@"; then
        echo "--- $name: passed"
    else
        local rc=$?
        echo "--- $name: FAILED (exit status $rc)"
        FAILED+=("$name (exit status $rc)")
    fi
}

set +e
suite "ruff" "$PY" -m ruff check .

# Static types: mypy --strict over agentsdk and the backends (as installed: see the script).
suite "mypy" "$PY" scripts/typecheck.py

# The API reference (docs/, Sphinx autodoc): docstring or cross-reference problems fail the build. Built as with
# the docs extra alone (pytest hidden from imports), and its pages checked: tests/test_docs_build.py's build, which
# the main suite below therefore leaves out (marker docs_build) rather than building the reference twice.
suite "sphinx" "$PY" scripts/docs_without_pytest.py build/docs

# Main suite (vcan- and netns-marked tests run below: this kernel has no CAN, and may lack netem), in two parts.
# First its files in parallel worker processes, one file per worker at a time (pytest-xdist; each worker's DDS
# tests pick their ROS domains from a share of their own: tests/ros_domains.py; TEST_WORKERS=0 runs them in
# this process). Then the tests marked `serial` alone: they run in realtime against wall-clock deadlines (a
# browser, signals, teleop, leases, realtime buses), and a second worker beside them is extra CPU load.
# (with arguments, e.g. -k NAME, one part may select no test: pytest's exit status 5 then is not a failure;
# without arguments every part must run tests)
part() {
    "$PY" -m pytest "$@"
    local rc=$?
    if [ $rc -eq 5 ] && [ "$NARGS" -gt 0 ]; then echo "(no test of this part selected)"; return 0; fi
    return $rc
}
NARGS=$#
suite "pytest (main suite)" part -m "not vcan and not netns and not serial and not docs_build" -n "${TEST_WORKERS:-2}" \
    --dist loadfile "$@"
suite "pytest (main suite, realtime tests alone)" part -m "serial and not vcan and not netns" "$@"

if [ "${SKIP_VCAN:-0}" != 1 ]; then
    # the VM's real-time tests share this machine's CPUs: show what else runs (a process the main suite
    # left behind would show up here)
    echo "--- load before the VM: $(cut -d' ' -f1-3 /proc/loadavg); busiest processes:"
    ps -eo pid=,etimes=,pcpu=,args= --sort=-pcpu 2>/dev/null | head -n 5 | cut -c1-160
    PYBIN=$("$PY" -c 'import sys; print(sys.executable)')
    # the same kernel also has network namespaces, veth and netem (as modules) for the ROS 2 network-fault tests
    suite "pytest (vcan and netns suites, real SocketCAN and netem inside user-mode Linux)" \
        env VCAN_EXTRA_MODS="drivers/net/veth.ko net/sched/sch_netem.ko" \
        bash scripts/run-in-vcan.sh "$PYBIN" -m pytest -m "vcan or netns" -p no:cacheprovider "$@"
fi

if [ ${#FAILED[@]} -ne 0 ]; then
    echo "=== FAILED: ${#FAILED[@]} suite(s)"
    printf '  %s\n' "${FAILED[@]}"
    exit 1
fi
echo "=== all suites passed"
