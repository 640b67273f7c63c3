#!/usr/bin/env bash
# Proves that the whole suite passes on a fresh machine of the project's kind: makes a
# clean Debian 12 root (debootstrap --variant=minbase), binds this machine's Rust
# toolchain into it, clones this checkout (its committed HEAD) inside, and runs .ci/run
# there exactly as CI does (CI=true). Everything else .ci/run and the tests need they must
# install themselves, as they would on a new machine.
#
#   sudo tests/fresh-root.sh [--keep] [ROOT]
#
# ROOT defaults to target/fresh-root (removed first, and afterwards unless --keep).
# HWGW_DEBIAN_MIRROR overrides the mirror (default: the one this machine's apt uses, else
# http://deb.debian.org/debian). Prints .ci/run's output and the wall time; exits with
# .ci/run's status.
set -euo pipefail

keep=false
if [ "${1:-}" = "--keep" ]; then
  keep=true
  shift
fi
src="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
root="${1:-$src/target/fresh-root}"
suite=bookworm

if [ "$(id -u)" != 0 ]; then
  echo "fresh-root: needs root (debootstrap, chroot, mounts)" >&2
  exit 2
fi
if ! command -v debootstrap >/dev/null; then
  echo "fresh-root: installing debootstrap"
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends debootstrap >/dev/null \
    || { apt-get update -q >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends debootstrap >/dev/null; }
fi
mirror="${HWGW_DEBIAN_MIRROR:-$(grep -hoE 'https?://[^ ]+/debian/?$' /etc/apt/sources.list /etc/apt/sources.list.d/*.sources /etc/apt/sources.list.d/*.list 2>/dev/null | head -n1 || true)}"
mirror="${mirror:-http://deb.debian.org/debian}"
rustup_home="${RUSTUP_HOME:-$HOME/.rustup}"
cargo_bin="${CARGO_HOME:-$HOME/.cargo}/bin"
[ -x "$cargo_bin/cargo" ] || { echo "fresh-root: no cargo in $cargo_bin" >&2; exit 2; }

mounts=()
cleanup() {
  for ((i = ${#mounts[@]} - 1; i >= 0; i--)); do
    umount -R -l "${mounts[$i]}" 2>/dev/null || true
  done
  if [ "$keep" = false ]; then
    rm -rf --one-file-system "$root"
  fi
}
trap cleanup EXIT
bind() { # bind SOURCE TARGET [ro]
  mkdir -p "$2"
  mount --rbind "$1" "$2"
  mount --make-rslave "$2"
  if [ "${3:-}" = ro ]; then mount -o remount,bind,ro "$2"; fi
  mounts+=("$2")
}

start=$(date +%s)
rm -rf --one-file-system "$root"
mkdir -p "$(dirname "$root")" # a new clone has no target/ yet
echo "fresh-root: debootstrap --variant=minbase $suite from $mirror into $root"
debootstrap --variant=minbase "$suite" "$root" "$mirror" >"$root.debootstrap.log" 2>&1 \
  || { tail -n 30 "$root.debootstrap.log" >&2; exit 1; }
rm -f "$root.debootstrap.log"
# The machine's own Debian suites (bookworm-security carries the 6.12 kernel the rig
# boots); third-party sources of the image are left out.
if [ -f /etc/apt/sources.list.d/debian.sources ]; then
  : >"$root/etc/apt/sources.list"
  cp /etc/apt/sources.list.d/debian.sources "$root/etc/apt/sources.list.d/"
else
  for s in "$suite" "$suite-updates"; do echo "deb $mirror $s main"; done >"$root/etc/apt/sources.list"
  echo "deb ${mirror%/debian}/debian-security $suite-security main" >>"$root/etc/apt/sources.list"
fi
cp /etc/resolv.conf "$root/etc/resolv.conf"
# What the Debian installer writes on every installed machine and debootstrap does not:
# without it `localhost` does not resolve (a deployment naming tcp/localhost:7447 would
# fail at run time, so `hwgw check` refuses it).
if [ ! -s "$root/etc/hosts" ]; then
  printf '127.0.0.1\tlocalhost\n::1\t\tlocalhost ip6-localhost ip6-loopback\n' >"$root/etc/hosts"
fi
# How this machine reaches its registries — apt's proxy and date settings, the local CAs
# of a TLS-inspecting egress (ca-certificates, which .ci/run installs, adds them to the
# bundle) — not anything it has installed.
for f in /etc/apt/apt.conf.d/*; do
  if grep -q '^Acquire::' "$f" 2>/dev/null; then cp "$f" "$root/etc/apt/apt.conf.d/"; fi
done
if compgen -G "/usr/local/share/ca-certificates/*.crt" >/dev/null; then
  mkdir -p "$root/usr/local/share/ca-certificates"
  cp /usr/local/share/ca-certificates/*.crt "$root/usr/local/share/ca-certificates/"
fi
echo "fresh-root: root ready after $(( $(date +%s) - start )) s: $(chroot "$root" dpkg-query -W | wc -l) packages"

mount -t proc proc "$root/proc"; mounts+=("$root/proc")
bind /sys "$root/sys"
bind /dev "$root/dev"
bind "$rustup_home" "$root/root/.rustup" ro
bind "$cargo_bin" "$root/root/.cargo/bin" ro
git clone --quiet --no-hardlinks "$src" "$root/build/hwgw"
echo "fresh-root: cloned $(git -C "$src" rev-parse --short HEAD); running .ci/run inside"

set +e
chroot "$root" /usr/bin/env -i \
  HOME=/root \
  PATH=/root/.cargo/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
  RUSTUP_HOME=/root/.rustup CARGO_HOME=/root/.cargo \
  LANG=C.UTF-8 TERM=dumb CI=true \
  /bin/bash -c 'cd /build/hwgw && bash .ci/run'
status=$?
set -e
end=$(date +%s)
echo "fresh-root: the build's target folder took $(du -sh "$root/build/hwgw/target" 2>/dev/null | cut -f1) (the disk CI needs beside the toolchain and packages)"
echo "fresh-root: .ci/run exited $status after $(( end - start )) s in all (a fresh Debian $suite minbase root, this machine's Rust toolchain)"
exit $status
