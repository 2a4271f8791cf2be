#!/usr/bin/env bash
# hil/pi-emulated-check.sh - magstack on an emulated 64-bit Raspberry Pi OS base (Debian 12 "bookworm", arm64,
# qemu user mode), installed as README.md / hil/README.md tell a Pi user, compared with this host.
#
#   sudo hil/pi-emulated-check.sh [--check] [--rebuild] [--no-demo] [--no-service]
#
# 1. checks its prerequisites (root, mmdebstrap, qemu-aarch64-static registered with binfmt_misc, git, a
#    magstack on this host) and stops with one line naming what is missing (exit 4);
# 2. builds an arm64 Debian 12 root with mmdebstrap (kept in $MAGSTACK_PI_WORK/root and reused; --rebuild);
# 3. copies this checkout (tracked and untracked, not ignored files) to /home/pi/magstack in the root and, as
#    user pi, follows the Pi recipe of hil/README.md: `apt-get install python3-venv python3-spidev` (root),
#    `python3 -m venv --system-site-packages ~/magstack-venv`, `~/magstack-venv/bin/pip install -e '.[pi]'` (the
#    flight install); checks that spidev came from Debian, lgpio from an aarch64 wheel, and that none of the
#    ground extra's libraries (scipy, pandas, matplotlib, pyerfa, ppigrf, threadpoolctl) was installed;
# 4. runs the simulated flight application (`magstack run --example-config`, then `magstack run --sim
#    --duration S`, virtual time) on both sides in the same absolute directory and compares every telemetry
#    file byte for byte, printing what differs;
# 5. measures the flight application's import time, CPU and wall time and peak resident memory on both sides
#    (benchmarks/bench_flight_footprint.py, `magstack run --sim --duration 60`, median of 3 runs);
# 6. runs the systemd service recipe of hil/README.md (the block after `<!-- service-recipe`) as user pi with
#    sudo, on a root made to look like Raspberry Pi OS (sudo, systemd, systemd-timesyncd, groups i2c/spi/gpio,
#    pi in group sudo without a password, /home/pi mode 0700), then checks the service user, the file modes,
#    that the install in /opt/magstack is not editable and is readable by the service user, that the unit is
#    enabled, and that the unit's command line, run as the service user on simulated sensors, stops on
#    SIGTERM with exit 143 and complete files; --no-service skips it;
# 7. installs the ground extra into the venv (`pip install -e '.[pi,ground]'`), runs `magstack demo` on both
#    sides and lists which artefacts are byte-identical (informational: the fitted floats may differ in the
#    last digit between platforms and library versions, docs/demo.md); --no-demo skips it.
#
# Exit status: 0 telemetry byte-identical and every check passed; 1 telemetry differs (listed); 4 a
# prerequisite is missing or a step or check failed (its log named). --check: only step 1. Logs and results:
# $MAGSTACK_PI_WORK (default /var/tmp/magstack-pi-check). Environment: MAGSTACK_PI_WORK, MAGSTACK_PI_RUN_S
# (virtual seconds of the flight run, default 600), MAGSTACK_HOST (the host's magstack command, default
# `magstack` on PATH), MAGSTACK_PI_MIRROR (mmdebstrap mirror arguments, default mmdebstrap's own),
# MAGSTACK_PI_CA_BUNDLE (CA certificates for pip inside the root, default the host's $PIP_CERT or
# $SSL_CERT_FILE, e.g. behind a TLS-intercepting proxy). hil/README.md says more.
set -euo pipefail

me=pi-emulated-check
here=${BASH_SOURCE[0]%/*}
[ "$here" = "${BASH_SOURCE[0]}" ] && here=.
repo=$(cd "$here/.." && pwd)
work=${MAGSTACK_PI_WORK:-/var/tmp/magstack-pi-check}
root=$work/root
run_s=${MAGSTACK_PI_RUN_S:-600}
host_magstack=${MAGSTACK_HOST:-magstack}
rundir=/tmp/magstack-pi-check   # the same absolute path on both sides (telemetry records table paths)
binfmt=/proc/sys/fs/binfmt_misc
check_only=0 rebuild=0 demo=1 service=1
for a in "$@"; do
    case $a in
        --check) check_only=1 ;;
        --rebuild) rebuild=1 ;;
        --no-demo) demo=0 ;;
        --no-service) service=0 ;;
        -h|--help) sed -n '2,/^set -euo/p' "${BASH_SOURCE[0]}" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
        *) echo "$me: unknown argument '$a' (--check, --rebuild, --no-demo, --no-service, --help)" >&2; exit 2 ;;
    esac
done

# 1. prerequisites --------------------------------------------------------------------------------------
missing=()
[ "$EUID" = 0 ] || missing+=("root (mmdebstrap and chroot need it: run with sudo)")
command -v mmdebstrap >/dev/null || missing+=("mmdebstrap (apt-get install mmdebstrap)")
command -v qemu-aarch64-static >/dev/null || missing+=("qemu-aarch64-static (apt-get install qemu-user-static)")
if [ ! -e "$binfmt/status" ]; then
    missing+=("binfmt_misc (mount -t binfmt_misc binfmt_misc $binfmt; a container needs a host that allows it)")
elif ! grep -qs '^enabled' "$binfmt/qemu-aarch64"; then
    missing+=("the qemu-aarch64 binfmt_misc handler (apt-get install binfmt-support qemu-user-static)")
fi
command -v git >/dev/null || missing+=("git")
command -v "$host_magstack" >/dev/null || missing+=("a magstack on this host ('$host_magstack'; set MAGSTACK_HOST)")
if [ ${#missing[@]} -gt 0 ]; then
    msg=$(printf '%s; ' "${missing[@]}")
    echo "$me: cannot run, missing: ${msg%; }" >&2
    exit 4
fi
if [ $check_only = 1 ]; then
    echo "$me: prerequisites present"
    exit 0
fi

mkdir -p "$work/logs"
t_all=$SECONDS
step=""
mounted=()
cleanup_mounts() { for m in "${mounted[@]}"; do umount -l "$m" 2>/dev/null || true; done; }
on_exit() {   # a step that failed (set -e) ends with one line naming it, exit 4
    local rc=$?
    cleanup_mounts
    if [ -n "$step" ] && [ $rc != 0 ]; then
        echo "$me: step \"$step\" failed (exit $rc; logs in $work/logs)" >&2
        exit 4
    fi
}
trap on_exit EXIT
die() { echo "$me: $*" >&2; step=""; exit 4; }
stage() { step=$1; t_step=$SECONDS; echo "$me: $1 ..."; }
took() { echo "$me:   done in $((SECONDS - t_step)) s"; }

# 2. the arm64 root --------------------------------------------------------------------------------------
if [ $rebuild = 1 ] || [ ! -x "$root/usr/bin/python3" ]; then
    stage "build the arm64 Debian 12 root (mmdebstrap)"
    rm -rf "$root"
    # shellcheck disable=SC2086 # MAGSTACK_PI_MIRROR holds mmdebstrap's mirror arguments
    mmdebstrap --arch=arm64 --variant=minbase --include=python3,python3-venv,ca-certificates,systemd,sudo \
        bookworm "$root" ${MAGSTACK_PI_MIRROR:-} >"$work/logs/mmdebstrap.log" 2>&1
    took
fi
[ "$(chroot "$root" uname -m)" = aarch64 ] || die "the root does not run as aarch64"

for m in proc dev; do
    if ! mountpoint -q "$root/$m"; then
        if [ $m = proc ]; then mount -t proc proc "$root/proc"; else mount --bind /dev "$root/dev"; fi
        mounted+=("$root/$m")
    fi
done
cp -L /etc/resolv.conf "$root/etc/resolv.conf"
# A host behind a TLS-intercepting proxy trusts an extra CA: pip inside the root gets the same bundle.
ca=${MAGSTACK_PI_CA_BUNDLE:-${PIP_CERT:-${SSL_CERT_FILE:-}}}
pip_cert=()
if [ -n "$ca" ]; then
    cp -L "$ca" "$root/etc/magstack-pi-ca.crt"
    pip_cert=(PIP_CERT=/etc/magstack-pi-ca.crt)
fi
as_pi() { chroot --userspec=1000:1000 "$root" /usr/bin/env -i HOME=/home/pi PATH=/usr/bin:/bin LANG=C.UTF-8 \
              "${pip_cert[@]}" /bin/sh -c "$1"; }

# 3. the flight install as hil/README.md says -----------------------------------------------------------------
stage "install magstack in a venv inside the root (flight install: '.[pi]')"
chroot "$root" /bin/sh -c 'id pi >/dev/null 2>&1 || useradd -m -u 1000 -s /bin/sh pi'
rm -rf "$root/home/pi/magstack" "$root/home/pi/magstack-venv"
mkdir -p "$root/home/pi/magstack"
git -C "$repo" ls-files -z -c -o --exclude-standard | (cd "$repo" && tar --null -T - -cf -) \
    | tar -xf - -C "$root/home/pi/magstack"
chroot "$root" chown -R pi:pi /home/pi/magstack
chroot "$root" /bin/sh -c 'apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q python3-venv python3-spidev' \
    >"$work/logs/apt.log" 2>&1
t_pip=$SECONDS
as_pi 'python3 -m venv --system-site-packages ~/magstack-venv &&
       cd ~/magstack && ~/magstack-venv/bin/pip install --progress-bar off -e ".[pi]"' >"$work/logs/pip.log" 2>&1
echo "$me:   pip install -e '.[pi]': $((SECONDS - t_pip)) s"
took
# located, not imported: importing lgpio creates its notification pipes in the current directory
where='import importlib.util, sys; print(importlib.util.find_spec(sys.argv[1]).origin)'
spidev_from=$(as_pi "~/magstack-venv/bin/python -c '$where' spidev")
lgpio_from=$(as_pi "~/magstack-venv/bin/python -c '$where' lgpio")
lgpio_wheel=$(grep -o 'lgpio-[^ ]*\.whl' "$work/logs/pip.log" | head -n 1 || true)
echo "$me:   spidev from $spidev_from"
echo "$me:   lgpio from $lgpio_from (${lgpio_wheel:-no wheel named in pip.log})"
case $spidev_from in /usr/lib/python3/dist-packages/*) ;; *) die "spidev did not come from Debian's python3-spidev" ;; esac
case $lgpio_wheel in *aarch64*) ;; *) die "lgpio was not installed from an aarch64 wheel (see $work/logs/pip.log)" ;; esac
if grep -q 'Building wheel for' "$work/logs/pip.log"; then
    echo "$me:   note: pip built from source: $(grep -o 'Building wheel for [^ ]*' "$work/logs/pip.log" | sort -u | tr '\n' ' ')"
fi
ground_libs='scipy pandas matplotlib erfa ppigrf threadpoolctl'
present=$(as_pi "~/magstack-venv/bin/python -c 'import importlib.util, sys
print(\" \".join(m for m in sys.argv[1:] if importlib.util.find_spec(m)))' $ground_libs")
[ -z "$present" ] || die "the flight install brought libraries of the ground extra: $present"
echo "$me:   flight install: none of $ground_libs installed; $(as_pi "~/magstack-venv/bin/pip list 2>/dev/null" \
    | tail -n +3 | wc -l) distributions in the venv"
ver='import platform, numpy, sys; print(platform.machine(), "Python", sys.version.split()[0], "numpy", numpy.__version__)'
host_python=$(head -n 1 "$(command -v "$host_magstack")" | sed -n 's/^#! *//p')
echo "$me:   arm64: $(as_pi "~/magstack-venv/bin/python -c '$ver'")"
echo "$me:   host:  $(${host_python:-python3} -c "$ver" 2>/dev/null || echo '?')"

# 4. the simulated flight application on both sides -------------------------------------------------------
flight='magstack run --example-config > flight.toml &&
        { magstack run --config flight.toml --sim --duration '"$run_s"' --out telemetry -q > run.txt; rc=$?;
          [ $rc = 0 ] || [ $rc = 1 ]; }'
stage "simulated flight run, $run_s s virtual, arm64 (qemu)"
rm -rf "$root$rundir"
as_pi "mkdir -p $rundir && cd $rundir && PATH=\$HOME/magstack-venv/bin:\$PATH && $flight" \
    >"$work/logs/run-arm64.log" 2>&1
took
stage "simulated flight run, $run_s s virtual, host"
rm -rf "$rundir" && mkdir -p "$rundir"
(set +e; cd "$rundir" && PATH=$(dirname "$(command -v "$host_magstack")"):$PATH && eval "$flight") \
    >"$work/logs/run-host.log" 2>&1
took
rm -rf "$work/arm64" "$work/host"
cp -r "$root$rundir" "$work/arm64"
cp -r "$rundir" "$work/host"

compare() {   # compare DIR_A DIR_B LABEL -> prints per-file verdicts, returns 1 when a file differs
    local a=$1 b=$2 label=$3 same=0 differ=0 f
    while IFS= read -r f; do
        if [ ! -e "$a/$f" ] || [ ! -e "$b/$f" ]; then
            echo "$me:   $label $f: only on $([ -e "$a/$f" ] && echo arm64 || echo host)"; differ=$((differ + 1))
        elif cmp -s "$a/$f" "$b/$f"; then
            same=$((same + 1))
        else
            differ=$((differ + 1))
            echo "$me:   $label $f differs: $(cmp "$a/$f" "$b/$f" 2>&1 | head -n 1)"
            case $f in *.csv|*.json|*.jsonl|*.txt|*.toml)
                diff "$a/$f" "$b/$f" | head -n 6 | sed "s/^/$me:     /" ;; esac
        fi
    done < <( (cd "$a" && find . -type f; cd "$b" && find . -type f) | sed 's|^\./||' | sort -u)
    echo "$me: $label: $same files byte-identical, $differ differ"
    [ $differ = 0 ]
}
verdict=0
compare "$work/arm64/telemetry" "$work/host/telemetry" telemetry || verdict=1

# 5. the flight application's footprint ----------------------------------------------------------------------
stage "footprint of magstack run --sim (import time, CPU, peak RSS), arm64 (qemu) and host"
bench=benchmarks/bench_flight_footprint.py
args='--config flight.toml --duration 60 --runs 3'
as_pi "cd $rundir && ~/magstack-venv/bin/python ~/magstack/$bench $args" >"$work/footprint-arm64.txt" \
    2>"$work/logs/footprint-arm64.log"
# shellcheck disable=SC2086 # $args: the benchmark's options
(cd "$rundir" && ${host_python:-python3} "$repo/$bench" $args) >"$work/footprint-host.txt" 2>"$work/logs/footprint-host.log"
sed "s/^/$me:   /" "$work/footprint-arm64.txt" "$work/footprint-host.txt"
took

# 6. the systemd service recipe of hil/README.md -------------------------------------------------------------
if [ $service = 1 ]; then
    stage "service recipe of hil/README.md, run as pi with sudo"
    # sudo is setuid: under qemu user mode the kernel honours that only with the handler's C (credentials) flag
    grep -q '^flags: .*C' "$binfmt/qemu-aarch64" || die "sudo cannot work inside the root: the qemu-aarch64 \
binfmt_misc handler lacks the C (credentials) flag (hil/README.md, 'Emulated Pi check', says how to add it)"
    # what Raspberry Pi OS has and a minbase Debian root lacks: sudo (pi without a password), systemd and its
    # NTP client, the device groups, home directories of mode 0700
    chroot "$root" /bin/sh -c 'DEBIAN_FRONTEND=noninteractive apt-get install -y -q sudo systemd systemd-timesyncd &&
        for g in i2c spi gpio; do getent group $g >/dev/null || groupadd --system $g; done &&
        usermod -aG sudo pi && echo "pi ALL=(ALL) NOPASSWD: ALL" > /etc/sudoers.d/010_pi-nopasswd &&
        chmod 0440 /etc/sudoers.d/010_pi-nopasswd && chmod 0700 /home/pi &&
        { grep -qw "$(hostname)" /etc/hosts || echo "127.0.1.1 $(hostname)" >> /etc/hosts; }' \
        >"$work/logs/service-prep.log" 2>&1
    # sudo clears the environment: a CA bundle given for pip (a TLS-intercepting proxy) goes to /etc/pip.conf,
    # which every user's pip reads (Raspberry Pi OS keeps its piwheels index there)
    if [ ${#pip_cert[@]} -gt 0 ]; then
        printf '[global]\ncert = /etc/magstack-pi-ca.crt\n' > "$root/etc/pip.conf"
    fi
    as_pi 'sudo -n true' >>"$work/logs/service-prep.log" 2>&1 || die "sudo does not work for pi inside the root \
(under qemu user mode a setuid binary needs the binfmt_misc handler's C flag: see hil/README.md)"
    # a previous run's service install is removed first, so the recipe runs as on a fresh Pi
    chroot "$root" /bin/sh -c 'rm -f /etc/systemd/system/magstack.service \
        /etc/systemd/system/multi-user.target.wants/magstack.service \
        /etc/systemd/system/sysinit.target.wants/systemd-time-wait-sync.service; rm -rf /opt/magstack /var/lib/magstack \
        /home/pi/magstack-dist; if id magstack >/dev/null 2>&1; then userdel magstack; fi;
        getent group magstack >/dev/null && groupdel magstack; true' >>"$work/logs/service-prep.log" 2>&1
    recipe=$(awk '/<!-- service-recipe/ {want=1; next} want && /^```sh$/ {inblock=1; next}
                  inblock && /^```$/ {exit} inblock {print}' "$repo/hil/README.md")
    [ -n "$recipe" ] || die "no service recipe block found in hil/README.md"
    printf '%s\n' "$recipe" > "$root/home/pi/service-recipe.sh"
    chroot "$root" chown pi:pi /home/pi/service-recipe.sh
    as_pi 'PATH=/usr/sbin:/usr/bin:/sbin:/bin; cd ~ && bash -x ~/service-recipe.sh' >"$work/logs/service-recipe.log" 2>&1 \
        || die "the service recipe failed (see $work/logs/service-recipe.log)"
    in_root() { chroot "$root" /bin/sh -c "$1"; }
    fail=()
    [ "$(in_root 'getent passwd magstack | cut -d: -f7')" = /usr/sbin/nologin ] || fail+=("magstack's shell is not nologin")
    [ "$(in_root 'id -u magstack')" -lt 1000 ] || fail+=("magstack is not a system user")
    for g in i2c spi gpio dialout; do
        in_root "id -nG magstack" | tr ' ' '\n' | grep -qx $g || fail+=("magstack is not in group $g")
    done
    modes=$(in_root 'stat -c "%n %U:%G %a" /opt/magstack /var/lib/magstack /var/lib/magstack/flight.toml \
        /var/lib/magstack/tables /etc/systemd/system/magstack.service')
    echo "$modes" | sed "s/^/$me:   /"
    printf '%s\n' "/opt/magstack root:root 755" "/var/lib/magstack magstack:magstack 750" \
        "/var/lib/magstack/flight.toml root:magstack 640" "/var/lib/magstack/tables magstack:magstack 750" \
        "/etc/systemd/system/magstack.service root:root 644" | while read -r want; do
        echo "$modes" | grep -qx "$want" || echo "$want"; done > "$work/modes-differ.txt"
    [ ! -s "$work/modes-differ.txt" ] || fail+=("modes differ from: $(tr '\n' ';' < "$work/modes-differ.txt")")
    umask_svc=$(in_root 'sed -n "s/^UMask=//p" /etc/systemd/system/magstack.service')
    as_svc() { chroot "$root" /usr/sbin/runuser -u magstack -- /bin/sh -c "umask ${umask_svc:-0022} && cd /var/lib/magstack && $1"; }
    origin=$(as_svc '/opt/magstack/bin/python -c "import magstack, sys; print(magstack.__file__)"')
    case $origin in /opt/magstack/lib/python3*/site-packages/magstack/__init__.py) ;;
        *) fail+=("magstack is imported from $origin, not from the install in /opt/magstack") ;; esac
    ! in_root 'ls /opt/magstack/lib/python3*/site-packages/' | grep -q '__editable__' || fail+=("the install is editable")
    present=$(in_root "/opt/magstack/bin/python -c 'import importlib.util, sys
print(\" \".join(m for m in sys.argv[1:] if importlib.util.find_spec(m)))' $ground_libs")
    [ -z "$present" ] || fail+=("the service install brought libraries of the ground extra: $present")
    in_root '[ -L /etc/systemd/system/multi-user.target.wants/magstack.service ]' || fail+=("magstack.service is not enabled")
    in_root 'ls /etc/systemd/system/*.wants/systemd-time-wait-sync.service' >/dev/null 2>&1 \
        || fail+=("systemd-time-wait-sync.service is not enabled")
    # the unit's command line as the service user, stopped as systemd stops it (SIGTERM); simulated sensors
    exec_start=$(in_root 'sed -n "s/^ExecStart=//p" /etc/systemd/system/magstack.service')
    set +e
    as_svc "$exec_start --sim --out /var/lib/magstack/sigterm-check -q & pid=\$!; sleep 40; kill -TERM \$pid;
            wait \$pid; echo exit=\$?" >"$work/logs/service-sigterm.log" 2>&1
    set -e
    grep -q '^exit=143$' "$work/logs/service-sigterm.log" || fail+=("the service command did not end with 143 on SIGTERM \
(see $work/logs/service-sigterm.log)")
    in_root 'ls /var/lib/magstack/sigterm-check/summary-*.json' >/dev/null 2>&1 \
        || fail+=("no summary written after SIGTERM")
    in_root 'ls /var/lib/magstack/sigterm-check/*.part' >/dev/null 2>&1 && fail+=("temporary files left after SIGTERM")
    tlm_mode=$(in_root 'stat -c "%U:%G %a" /var/lib/magstack/sigterm-check/summary-0001.json' || true)
    [ "$tlm_mode" = "magstack:magstack 640" ] || fail+=("telemetry written as $tlm_mode, not magstack:magstack 640")
    grep -E 'systemd-analyze verify' -A3 "$work/logs/service-recipe.log" | sed "s/^/$me:   /"
    if [ ${#fail[@]} -gt 0 ]; then
        die "service recipe: $(printf '%s; ' "${fail[@]}")"
    fi
    echo "$me:   service recipe ran; user, modes, a non-editable lean install, enabled unit, SIGTERM -> 143: as stated"
    took
fi

# 7. the ground extra and the demo (informational) -----------------------------------------------------------
if [ $demo = 1 ]; then
    stage "pip install -e '.[pi,ground]' (the ground tools), arm64 (qemu)"
    t_pip=$SECONDS
    as_pi 'cd ~/magstack && ~/magstack-venv/bin/pip install --progress-bar off -e ".[pi,ground]"' \
        >"$work/logs/pip-ground.log" 2>&1
    echo "$me:   pip install -e '.[pi,ground]' on top of the flight install: $((SECONDS - t_pip)) s"
    took
    stage "magstack demo, arm64 (qemu)"
    as_pi "cd $rundir && \$HOME/magstack-venv/bin/magstack demo --out demo -q" >"$work/logs/demo-arm64.log" 2>&1
    took
    stage "magstack demo, host"
    (cd "$rundir" && "$host_magstack" demo --out demo -q) >"$work/logs/demo-host.log" 2>&1
    took
    rm -rf "$work/arm64-demo" "$work/host-demo"
    cp -r "$root$rundir/demo" "$work/arm64-demo"
    cp -r "$rundir/demo" "$work/host-demo"
    compare "$work/arm64-demo" "$work/host-demo" demo || true
fi

step=""
echo "$me: total $((SECONDS - t_all)) s wall; telemetry $([ $verdict = 0 ] && echo byte-identical || echo DIFFERS)"
exit $verdict
