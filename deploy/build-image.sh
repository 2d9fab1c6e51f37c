#!/usr/bin/env bash
# Builds the lcrl container image (default tag lcrl:local) without pulling
# anything: the image is FROM scratch and holds the lcrl binaries, exactly
# the shared libraries they load, and configs/. The same debug-profile
# binaries the tests run are used (one build profile for everything), with
# debug sections stripped.
#   bash deploy/build-image.sh [TAG]
set -euo pipefail
cd "$(dirname "$0")/.."
tag="${1:-lcrl:local}"
bash scripts/setup.sh >/dev/null
# Started by a test (the compose end-to-end test), this shell inherits what
# cargo sets for a test process (CARGO_MANIFEST_DIR, CARGO_PKG_*, OUT_DIR,
# ...). Build scripts such as ring's rerun when those change, so the build
# below would recompile ring and the 15 crates above it (about 36 s on 2
# cores), and the next plain `cargo build` all of them again.
while read -r var; do unset "$var"; done < <(compgen -e | grep -E '^(CARGO_PKG_|CARGO_MANIFEST_|CARGO_CRATE_NAME$|CARGO_BIN_|CARGO_PRIMARY_PACKAGE$|CARGO_TARGET_TMPDIR$|OUT_DIR$)')
cargo build --workspace --bins
stage=target/image
rm -rf "$stage"
mkdir -p "$stage/rootfs/bin" "$stage/rootfs/lib" "$stage/rootfs/lib64" "$stage/rootfs/configs" "$stage/rootfs/runs" "$stage/rootfs/tmp" "$stage/rootfs/dev/shm"
chmod 1777 "$stage/rootfs/tmp"
bins=(lcrl lcrl-learner lcrl-actor lcrl-graph-builder)
for bin in "${bins[@]}"; do
  objcopy --strip-debug "target/debug/$bin" "$stage/rootfs/bin/$bin"
done
# Every library any binary loads, resolved as the dynamic loader would
# (rpath into .venv/libtorch included); copied by content, not as links.
for bin in "${bins[@]}"; do
  ldd "target/debug/$bin" | awk '/=> \// { print $3 } /^[ \t]*\/.*ld-linux/ { print $1 }'
done | sort -u | while read -r lib; do
  case "$lib" in
    */ld-linux-x86-64.so.2) cp -L "$lib" "$stage/rootfs/lib64/ld-linux-x86-64.so.2" ;;
    *) cp -L "$lib" "$stage/rootfs/lib/" ;;
  esac
done
if ldd target/debug/lcrl-learner | grep -q "not found"; then
  echo "build-image: a library of lcrl-learner is missing:" >&2
  ldd target/debug/lcrl-learner | grep "not found" >&2
  exit 1
fi
cp configs/*.toml "$stage/rootfs/configs/"
cp deploy/Dockerfile "$stage/Dockerfile"
echo "build-image: staged $(du -sh "$stage/rootfs" | cut -f1) ($(ls "$stage/rootfs/lib" | wc -l) libraries); building $tag"
docker build --quiet -t "$tag" "$stage" >/dev/null
echo "build-image: $tag is $(docker image inspect "$tag" --format '{{.Size}}' | awk '{ printf "%.0f MB", $1 / 1e6 }')"
