#!/usr/bin/env bash
# Our 3D gradient noise against FastNoise2's Perlin (and FastNoise Lite's),
# one thread: shared/bench-fastnoise2, a crate outside the workspace, so the
# test command never builds FastNoise2. Installs Debian's cmake, g++, clang
# and libclang-dev when missing, copies the FastNoise2 source vendored in the
# `fastnoise2-sys` crate to target/fastnoise2-src with FastSIMD taken from
# the team folder's FastSIMD (FastNoise2's CMake fetches it from the network
# otherwise), builds offline and runs the benchmark pinned to CPU $CPU
# (default 1). Arguments go to the benchmark (rounds, default 11).
#
# FASTSIMD=/path/to/FastSIMD overrides the FastSIMD source (default: the
# team folder's /work/shared/data/FastSIMD).
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
crate="$root/shared/bench-fastnoise2"
fastsimd="${FASTSIMD:-/work/shared/data/FastSIMD}"
[ -f "$fastsimd/CMakeLists.txt" ] || { echo "no FastSIMD source at $fastsimd" >&2; exit 1; }

missing=()
for pkg in cmake g++ clang libclang-dev; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q 'install ok installed' || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo=sudo
    $sudo apt-get install -y "${missing[@]}"
fi

cargo fetch --locked --manifest-path "$crate/Cargo.toml"
registry="${CARGO_HOME:-$HOME/.cargo}/registry/src"
version="$(cargo metadata --locked --format-version 1 --manifest-path "$crate/Cargo.toml" \
    | python3 -c 'import json, sys
print(next(p["version"] for p in json.load(sys.stdin)["packages"] if p["name"] == "fastnoise2-sys"))')"
vendored="$(ls -d "$registry"/*/"fastnoise2-sys-$version"/build/FastNoise2 | head -n 1)"

src="$root/target/fastnoise2-src"
stamp="$src/.from"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$vendored $fastsimd" ]; then
    rm -rf "$src"
    mkdir -p "$root/target"
    cp -r "$vendored" "$src"
    { echo "set(CPM_FastSIMD_SOURCE $fastsimd)"; cat "$vendored/src/CMakeLists.txt"; } \
        > "$src/src/CMakeLists.txt"
    echo "$vendored $fastsimd" > "$stamp"
fi

export FASTNOISE2_SOURCE_DIR="$src"
export CARGO_TARGET_DIR="$root/target/bench-fastnoise2"
cargo build --release --locked --offline --manifest-path "$crate/Cargo.toml"
taskset -c "${CPU:-1}" "$CARGO_TARGET_DIR/release/bench-fastnoise2" "$@"
