#!/usr/bin/env bash
# hil/pi-emulated-check.sh - magstack on an emulated 64-bit Raspberry Pi OS base (Debian 12 "bookworm", arm64,
# qemu user mode), installed as README.md / hil/README.md tell a Pi user, compared with this host.
#
#   sudo hil/pi-emulated-check.sh [--check] [--rebuild] [--no-demo]
#
# 1. checks its prerequisites (root, mmdebstrap, qemu-aarch64-static registered with binfmt_misc, git, a
#    magstack on this host) and stops with one line naming what is missing (exit 4);
# 2. builds an arm64 Debian 12 root with mmdebstrap (kept in $MAGSTACK_PI_WORK/root and reused; --rebuild);
# 3. copies this checkout (tracked and untracked, not ignored files) to /home/pi/magstack in the root and, as
#    user pi, follows the README's Pi recipe: `apt update && apt install python3-spidev` (root), `python3 -m venv
#    --system-site-packages ~/magstack-venv`, `~/magstack-venv/bin/pip install -e '.[pi]'`; then checks that
#    spidev came from Debian and lgpio from an aarch64 wheel;
# 4. runs the simulated flight application (`magstack run --example-config`, then `magstack run --sim
#    --duration S`, virtual time) on both sides in the same absolute directory and compares every telemetry
#    file byte for byte, printing what differs;
# 5. runs `magstack demo` on both sides and lists which artefacts are byte-identical (informational: the
#    fitted floats may differ in the last digit between platforms and library versions, docs/demo.md).
#
# Exit status: 0 telemetry byte-identical; 1 telemetry differs (listed); 4 a prerequisite is missing or a
# step failed (its log named). --check: only step 1. Logs and results: $MAGSTACK_PI_WORK (default
# /var/tmp/magstack-pi-check). Environment: MAGSTACK_PI_WORK, MAGSTACK_PI_RUN_S (virtual seconds of the
# flight run, default 600), MAGSTACK_HOST (the host's magstack command, default `magstack` on PATH),
# MAGSTACK_PI_MIRROR (mmdebstrap mirror arguments, default mmdebstrap's own), MAGSTACK_PI_CA_BUNDLE (CA
# certificates for pip inside the root, default the host's $PIP_CERT or $SSL_CERT_FILE, e.g. behind a
# TLS-intercepting proxy). hil/README.md says more.
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
check_only=0 rebuild=0 demo=1
for a in "$@"; do
    case $a in
        --check) check_only=1 ;;
        --rebuild) rebuild=1 ;;
        --no-demo) demo=0 ;;
        -h|--help) sed -n '2,/^set -euo/p' "${BASH_SOURCE[0]}" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
        *) echo "$me: unknown argument '$a' (--check, --rebuild, --no-demo, --help)" >&2; exit 2 ;;
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
    mmdebstrap --arch=arm64 --variant=minbase --include=python3,python3-venv,ca-certificates \
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

# 3. install as README.md says ---------------------------------------------------------------------------
stage "install magstack in a venv inside the root (README recipe)"
chroot "$root" /bin/sh -c 'id pi >/dev/null 2>&1 || useradd -m -u 1000 -s /bin/sh pi'
rm -rf "$root/home/pi/magstack" "$root/home/pi/magstack-venv"
mkdir -p "$root/home/pi/magstack"
git -C "$repo" ls-files -z -c -o --exclude-standard | (cd "$repo" && tar --null -T - -cf -) \
    | tar -xf - -C "$root/home/pi/magstack"
chroot "$root" chown -R pi:pi /home/pi/magstack
chroot "$root" /bin/sh -c 'apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q python3-spidev' \
    >"$work/logs/apt.log" 2>&1
as_pi 'python3 -m venv --system-site-packages ~/magstack-venv &&
       cd ~/magstack && ~/magstack-venv/bin/pip install --progress-bar off -e ".[pi]"' >"$work/logs/pip.log" 2>&1
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

# 5. the demo (informational) ------------------------------------------------------------------------------
if [ $demo = 1 ]; then
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
