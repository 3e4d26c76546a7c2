#!/bin/bash
# run-in-vcan.sh - run a command inside a User-Mode-Linux kernel that has a
# real SocketCAN "vcan0" interface, with the host's filesystem as root.
#
#   usage: scripts/run-in-vcan.sh [--] COMMAND [ARGS...]
#   e.g.   scripts/run-in-vcan.sh python -m pytest -m vcan -p no:cacheprovider
#
# Used by scripts/test.sh for the vcan-marked tests; on a machine whose kernel
# has CAN support you can instead `ip link add vcan0 type vcan` and run pytest.
# Self-contained: needs only bash, coreutils, iproute2 (`ip`) and either kmod's
# insmod or python3 on the host, plus the user-mode-linux package (installed
# automatically with apt-get when running as root).
#
# * Boots Debian's user-mode-linux kernel (apt package "user-mode-linux",
#   6.1.x, CAN/CAN_RAW/CAN_BCM/CAN_GW/CAN_J1939/CAN_VCAN/CAN_VXCAN as modules)
#   as an ordinary process: no KVM, no root image, no network needed.
# * Root filesystem = the host's "/" via hostfs (read-write!), so venvs,
#   the project checkout, /tmp, etc. are visible at the same paths. Files the
#   command writes land on the host, owned by the user running this script.
# * Inside: loads can, can-raw, can-bcm, can-gw, can-dev, vcan, vxcan,
#   can-j1939; runs `ip link add dev vcan0 type vcan && ip link set up vcan0`
#   (more with VCAN_IFACES="vcan0 vcan1"), then runs COMMAND in the current
#   directory with the caller's exported environment.
# * COMMAND's stdout/stderr are streamed to this script's stdout/stderr,
#   and its exit status is this script's exit status. 125 = the VM itself
#   failed (boot log is printed), 124 = VCAN_TIMEOUT expired.
#
# Environment knobs:
#   VCAN_MEM=1G           guest RAM (sparse tmpfs-backed file, only used pages count)
#   VCAN_TIMEOUT=3600     seconds before the whole VM is killed
#   VCAN_IFACES=vcan0     vcan interfaces to create
#   VCAN_RMEM=4194304     guest net.core.rmem_default/rmem_max (0 = kernel default
#                         212992). UML has one vCPU and slow syscalls, so a reader
#                         thread falls behind a flooding writer more often than on
#                         real hardware; with the default buffer 2 of ~140 runs of
#                         a 1000-frame burst lost frames to rx-socket overflow.
#   VCAN_STATE_DIR=/tmp/run_in_vcan   where per-run scratch dirs go
#   VCAN_AUTO_INSTALL=1   apt-get install user-mode-linux if linux.uml is missing
#   VCAN_KEEP=0           1 = keep the per-run scratch dir (boot log etc.)
#   VCAN_VERBOSE=0        1 = print the kernel boot log to stderr afterwards
#   VCAN_UML_TMPDIR=/dev/shm  where UML puts its (unlinked) guest-RAM file
#   VCAN_INSMOD=path      module loader; set empty to force the python fallback
#   VCAN_EXTRA_MODS=""    more modules to load (paths under the UML kernel/ dir), e.g.
#                         "drivers/net/veth.ko net/sched/sch_netem.ko" for the network-
#                         namespace tests (the host kernel may lack netem)
set -u -o pipefail

[ "${1:-}" = "--" ] && shift
if [ $# -eq 0 ]; then
    echo "usage: $0 [--] COMMAND [ARGS...]" >&2
    exit 2
fi

MEM=${VCAN_MEM:-1G}
TIMEOUT=${VCAN_TIMEOUT:-3600}
IFACES=${VCAN_IFACES:-vcan0}
STATE_DIR=${VCAN_STATE_DIR:-/tmp/run_in_vcan}
RMEM=${VCAN_RMEM:-4194304}
UML=${VCAN_UML:-/usr/bin/linux.uml}

die() { echo "run_in_vcan: $*" >&2; exit 125; }

# ---------------------------------------------------------------- kernel
if [ ! -x "$UML" ]; then
    if [ "${VCAN_AUTO_INSTALL:-1}" = 1 ] && [ "$(id -u)" = 0 ]; then
        echo "run_in_vcan: installing user-mode-linux (~41 MB download)..." >&2
        export DEBIAN_FRONTEND=noninteractive
        apt-get install -y -q --no-install-recommends user-mode-linux >&2 ||
            { apt-get update -q >&2 &&
              apt-get install -y -q --no-install-recommends user-mode-linux >&2; } ||
            die "apt-get install user-mode-linux failed"
    fi
    [ -x "$UML" ] || die "$UML not found (apt-get install user-mode-linux)"
fi
KVER=$(ls /usr/lib/uml/modules 2>/dev/null | sort -V | tail -n1)
MODDIR=/usr/lib/uml/modules/$KVER/kernel
[ -n "$KVER" ] && [ -f "$MODDIR/drivers/net/can/vcan.ko" ] ||
    die "no vcan.ko under /usr/lib/uml/modules (is user-mode-linux installed?)"

# A python3 with ctypes is the fallback module loader when kmod's insmod is absent.
HOST_PY=""
for p in /usr/bin/python3 "$(command -v python3 2>/dev/null)"; do
    if [ -n "$p" ] && [ -x "$p" ]; then HOST_PY=$p; break; fi
done
INSMOD=${VCAN_INSMOD-$(command -v insmod 2>/dev/null || true)}  # VCAN_INSMOD= forces the python loader
[ -n "$INSMOD" ] || [ -n "$HOST_PY" ] || die "need either kmod's insmod or python3 on the host"
IP=$(command -v ip 2>/dev/null) || die "need iproute2's ip on the host"
BASH_BIN=$(command -v bash)

# ---------------------------------------------------------------- per-run dir
mkdir -p "$STATE_DIR" || die "cannot create $STATE_DIR"
RUN=$(mktemp -d "$STATE_DIR/run.XXXXXX") || die "mktemp failed"
cleanup() {
    [ -n "${OUT_PID:-}" ] && wait "$OUT_PID" 2>/dev/null
    [ -n "${ERR_PID:-}" ] && wait "$ERR_PID" 2>/dev/null
    if [ "${VCAN_KEEP:-0}" = 1 ]; then echo "run_in_vcan: kept $RUN" >&2; else rm -rf "$RUN"; fi
}
trap cleanup EXIT

# Command, working directory and exported environment for the guest.
printf '%q ' "$@" > "$RUN/cmd"
printf '%q' "$PWD" > "$RUN/cwd"
export -p | grep -v -E '^declare -x (PWD|OLDPWD|SHLVL|_|TMPDIR)(=|$)' > "$RUN/env"
[ -n "${TMPDIR:-}" ] && printf 'export TMPDIR=%q\n' "$TMPDIR" >> "$RUN/env"

# Guest PID 1: a bash script run from the host filesystem.
cat > "$RUN/init" <<EOF
#!$BASH_BIN
# PID 1 inside user-mode-linux (generated by run-in-vcan.sh)
RUN=$(printf %q "$RUN")
MODDIR=$(printf %q "$MODDIR")
INSMOD=$(printf %q "$INSMOD")
HOST_PY=$(printf %q "$HOST_PY")
IP=$(printf %q "$IP")
IFACES=$(printf %q "$IFACES")
RMEM=$(printf %q "$RMEM")
EXTRA_MODS=$(printf %q "${VCAN_EXTRA_MODS:-}")
export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
finish() {          # record status, flush, power off (UML exits on the host)
    echo "\$1" > "\$RUN/rc.tmp" && mv "\$RUN/rc.tmp" "\$RUN/rc"
    sync
    poweroff -f -f 2>/dev/null || echo o > /proc/sysrq-trigger
    sleep 10
}
log() { echo "[guest \$(cut -d" " -f1 /proc/uptime)s] \$*" >&2; }   # goes to the kernel log channel (fd 2 = /dev/console)
exec </dev/null >/dev/console 2>&1
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mountpoint -q /dev || mount -t devtmpfs devtmpfs /dev
mkdir -p /dev/pts /dev/shm
mount -t devpts -o gid=5,mode=620,ptmxmode=666 devpts /dev/pts
mount -t tmpfs -o mode=1777 tmpfs /dev/shm
mount -t tmpfs -o mode=755 tmpfs /run
log "init started"
\$IP link set lo up
MODS="net/can/can.ko net/can/can-raw.ko net/can/can-bcm.ko net/can/can-gw.ko
      drivers/net/can/dev/can-dev.ko drivers/net/can/vcan.ko
      drivers/net/can/vxcan.ko net/can/j1939/can-j1939.ko \$EXTRA_MODS"
if [ -n "\$INSMOD" ]; then
    for m in \$MODS; do
        "\$INSMOD" "\$MODDIR/\$m" || { log "insmod \$m failed"; finish 125; }
    done
else    # no kmod on the host: finit_module(2) via python ctypes, one process for all
    (cd "\$MODDIR" && "\$HOST_PY" -c 'import ctypes,os,sys
libc=ctypes.CDLL(None,use_errno=True)
for m in sys.argv[1:]:
    fd=os.open(m,os.O_RDONLY)
    if libc.syscall(313,fd,b"",0) and ctypes.get_errno()!=17:  # SYS_finit_module, EEXIST ok
        sys.exit("finit_module(%s): %s"%(m,os.strerror(ctypes.get_errno())))
    os.close(fd)' \$MODS) || { log "loading CAN modules failed"; finish 125; }
fi
log "modules loaded"
for i in \$IFACES; do
    \$IP link add dev "\$i" type vcan && \$IP link set up "\$i" ||
        { log "creating \$i failed"; finish 125; }
done
if [ "\$RMEM" != 0 ]; then   # bigger default socket buffers: fewer rx overflows on 1 vCPU
    echo "\$RMEM" > /proc/sys/net/core/rmem_max && echo "\$RMEM" > /proc/sys/net/core/rmem_default
fi
log "vcan up: \$(\$IP -br link show type vcan | tr -s ' \n' ' ')"
# Command stdout -> ttyS0 -> host stdout, stderr -> ttyS1 -> host stderr.
# The command sees pipes (not a tty), like under a CI runner.
stty -F /dev/ttyS0 raw -echo 2>/dev/null; stty -F /dev/ttyS1 raw -echo 2>/dev/null
exec 3>/dev/ttyS0 4>/dev/ttyS1
mkfifo /run/vcan_out /run/vcan_err
cat /run/vcan_out >&3 & PO=\$!
cat /run/vcan_err >&4 & PE=\$!
set -a; . "\$RUN/env"; set +a
eval "cd -- \$(cat "\$RUN/cwd")" || { log "cannot cd"; finish 125; }
log "starting command"
eval "\$(cat "\$RUN/cmd")" </dev/null >/run/vcan_out 2>/run/vcan_err 3>&- 4>&-
rc=\$?
# let the output drain (bounded, in case a leftover daemon keeps a pipe open)
for _ in \$(seq 100); do kill -0 \$PO 2>/dev/null || kill -0 \$PE 2>/dev/null || break; sleep 0.05; done
kill -0 \$PO 2>/dev/null || kill -0 \$PE 2>/dev/null || wait
log "command exited \$rc"
finish "\$rc"
EOF
chmod +x "$RUN/init"

# ---------------------------------------------------------------- boot
# UML backs guest RAM with an (immediately unlinked) file in $TMPDIR: prefer tmpfs.
UML_TMP=${VCAN_UML_TMPDIR:-/dev/shm}
[ -d "$UML_TMP" ] && [ -w "$UML_TMP" ] || UML_TMP=$RUN

# Fresh pipes for the guest's stdout/stderr: UML puts its channel fds into
# O_NONBLOCK mode, which must not leak into the caller's stdout/stderr.
exec {GOUT}> >(cat); OUT_PID=$!
exec {GERR}> >(cat >&2); ERR_PID=$!

START=$(date +%s.%N)
# (timeout puts itself and UML's helper processes in one process group and
# kills the whole group when the time is up or when it gets SIGTERM itself.)
TMPDIR=$UML_TMP timeout -k 10 "$TIMEOUT" "$UML" \
    mem="$MEM" uml_dir="$RUN" umid=vm \
    root=/dev/root rootfstype=hostfs rootflags=/ rw \
    init="$RUN/init" \
    con=null ssl=null con0=null,fd:2 ssl0=null,fd:$GOUT ssl1=null,fd:$GERR \
    </dev/null >"$RUN/boot.log" 2>&1 &
UML_PID=$!
trap 'kill -TERM "$UML_PID" 2>/dev/null; INTERRUPTED=1' INT TERM
INTERRUPTED=0
while :; do
    wait "$UML_PID"; UML_RC=$?
    kill -0 "$UML_PID" 2>/dev/null || break     # wait was cut short by a signal
done
trap - INT TERM
exec {GOUT}>&- {GERR}>&-
wait "$OUT_PID" "$ERR_PID" 2>/dev/null; OUT_PID=; ERR_PID=
END=$(date +%s.%N)

[ "${VCAN_VERBOSE:-0}" = 1 ] && { echo "----- UML log ($RUN/boot.log)" >&2; cat "$RUN/boot.log" >&2; }
if [ "$INTERRUPTED" = 1 ]; then
    echo "run_in_vcan: interrupted; VM stopped" >&2
    exit 130
fi
if [ "$UML_RC" = 124 ] || [ "$UML_RC" = 137 ]; then
    echo "run_in_vcan: timed out after ${TIMEOUT}s; last kernel log lines:" >&2
    tail -n 30 "$RUN/boot.log" >&2
    exit 124
fi
if [ ! -f "$RUN/rc" ]; then
    echo "run_in_vcan: VM ended (linux.uml rc=$UML_RC) without a result; kernel log tail:" >&2
    tail -n 40 "$RUN/boot.log" >&2
    exit 125
fi
RC=$(cat "$RUN/rc")
echo "run_in_vcan: guest command exited $RC ($(awk "BEGIN{printf \"%.1f\", $END-$START}")s incl. boot)" >&2
exit "$RC"
