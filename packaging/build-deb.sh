#!/bin/sh
# Builds the Debian package hwgw_<version>-<revision>_<arch>.deb (docs/install.md):
#
#   packaging/build-deb.sh [--binary PATH] [--output DIR] [cargo-deb options...]
#
# 1. builds the release binary (cargo build --release -p hwgw), unless --binary names one
#    already built (the kernel rig test packages the binary cargo built for it);
# 2. generates the manual pages and the bash, zsh and fish completions from that binary's
#    own command line (`hwgw generate-assets`, hidden from --help);
# 3. runs `cargo deb -p hwgw --no-build` (metadata: [package.metadata.deb] in
#    gateway/Cargo.toml) on a staging directory that holds the binary and those files as
#    target/release/ would, so nothing is built twice: cargo-deb strips the binary, computes
#    Depends with dpkg-shlibdeps and writes the maintainer scripts.
#
# The .deb goes to DIR (default: target/debian/); its path is printed last. Options after
# ours go to cargo-deb, e.g. --deb-revision 2, --deb-version 0.1.0+1-1, --fast (lighter
# compression). cargo-deb itself is installed, at the version pinned here, when missing.
set -eu

CARGO_DEB_VERSION=3.7.0

binary=
output=
while [ $# -gt 0 ]; do
	case "$1" in
	--binary) binary=$2; shift 2 ;;
	--output) output=$2; shift 2 ;;
	-h | --help) sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
	*) break ;;
	esac
done

cd "$(dirname "$0")/.."
target=$(cargo metadata --format-version 1 --no-deps |
	sed -n 's/.*"target_directory":"\([^"]*\)".*/\1/p')
[ -n "$target" ] || { echo "build-deb: cargo metadata named no target directory" >&2; exit 1; }

# cargo-deb at the pinned version: the one on the PATH, or one installed under the target
# directory (not in ~/.cargo/bin, which may be read-only, as in tests/fresh-root.sh).
cargo_deb() { cargo deb "$@"; }
if [ "$(cargo deb --version 2>/dev/null || true)" != "cargo-deb $CARGO_DEB_VERSION" ]; then
	tools=$target/tools/cargo-deb-$CARGO_DEB_VERSION
	if [ ! -x "$tools/bin/cargo-deb" ]; then
		echo "build-deb: installing cargo-deb $CARGO_DEB_VERSION into $tools" >&2
		cargo install cargo-deb --locked --version "$CARGO_DEB_VERSION" --root "$tools" >&2 || {
			echo "build-deb: cargo-deb $CARGO_DEB_VERSION is missing and could not be installed" \
				"(cargo install cargo-deb --locked --version $CARGO_DEB_VERSION)" >&2
			exit 1
		}
	fi
	cargo_deb() { "$tools/bin/cargo-deb" deb "$@"; }
fi

if [ -z "$binary" ]; then
	cargo build --release --locked -p hwgw >&2
	binary=$target/release/hwgw
fi
[ -x "$binary" ] || { echo "build-deb: $binary: no such program" >&2; exit 1; }
binary=$(realpath "$binary")

mkdir -p "$target"
stage=$(mktemp -d "$target/deb-stage.XXXXXX")
trap 'rm -rf "$stage"' EXIT
mkdir "$stage/release"
ln -s "$binary" "$stage/release/hwgw"
"$binary" generate-assets "$stage/release/assets" >/dev/null
# Debian compresses manual pages (cargo-deb leaves files under target/ as they are).
gzip -9n "$stage/release/assets/man/"*.1

output=${output:-$target/debian}
mkdir -p "$output"
# cargo-deb takes target/release/ from CARGO_TARGET_DIR: the staging directory.
(
	CARGO_TARGET_DIR=$stage
	export CARGO_TARGET_DIR
	cargo_deb -p hwgw --no-build --output "$output" "$@"
)
