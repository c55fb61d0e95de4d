#!/usr/bin/env bash
# What the vm test stage needs: qemu and the guest's tools (Debian packages), a pinned Debian kernel
# unpacked into a cache folder (never installed), and virtme-ng in its own virtual environment.
# Safe to run twice: each part is skipped when it is already there. Run as root (apt-get).
# The cache folder: $SELFVIEW_VM_CACHE, default ~/.cache/selfview-vm (tests/vm/stage.py reads the same).
set -euo pipefail
KERNEL_PACKAGE=linux-image-6.1.0-57-amd64
VIRTME_NG=virtme-ng==1.42
PACKAGES=(qemu-system-x86 v4l-utils kmod busybox-static)
cache="${SELFVIEW_VM_CACHE:-$HOME/.cache/selfview-vm}"
t0=$(date +%s)
mkdir -p "$cache"

missing=()
for p in "${PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
    echo "setup: installing ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -q </dev/null
    apt-get install -y -q --no-install-recommends "${missing[@]}" </dev/null
else
    echo "setup: Debian packages already installed"
fi

kdir="$cache/$KERNEL_PACKAGE"
if [ ! -e "$kdir/.complete" ]; then
    echo "setup: unpacking $KERNEL_PACKAGE into the cache"
    rm -rf "$kdir" "$cache/deb"
    mkdir -p "$cache/deb"
    (cd "$cache/deb" && apt-get download -q -o APT::Sandbox::User=root "$KERNEL_PACKAGE" </dev/null)
    dpkg-deb -x "$cache"/deb/"$KERNEL_PACKAGE"_*.deb "$kdir"
    rm -rf "$cache/deb"
    touch "$kdir/.complete"
else
    echo "setup: $KERNEL_PACKAGE already unpacked"
fi

have=""
[ -x "$cache/venv/bin/vng" ] && have=$("$cache/venv/bin/python" -c \
    'import importlib.metadata as m; print(m.version("virtme-ng"))' 2>/dev/null || true)
if [ "$have" != "${VIRTME_NG#*==}" ]; then
    echo "setup: installing $VIRTME_NG"
    python3 -m venv "$cache/venv"
    "$cache/venv/bin/pip" install -q "$VIRTME_NG" </dev/null
else
    echo "setup: $VIRTME_NG already installed"
fi
echo "setup: done in $(( $(date +%s) - t0 )) s (cache $cache)"
