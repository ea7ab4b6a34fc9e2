#!/usr/bin/env bash
# Renders every gallery scene at 256×256 into docs/gallery/ (the README's pictures).
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -p coordinator
bin=${CARGO_TARGET_DIR:-target}/release/coordinator
out=${1:-docs/gallery}
mkdir -p "$out"
for scene in scenes/*.ron; do
    name=$(basename "$scene" .ron)
    "$bin" --scene "$scene" --out "$out/$name.png" --width 256 --height 256
done
# Gilet & Dischler's scenes, prefixed gilet_.
for scene in scenes/gilet/*.ron; do
    name=$(basename "$scene" .ron)
    "$bin" --scene "$scene" --out "$out/gilet_$name.png" --width 256 --height 256
done

# Meshes (scenes/mesh/), as mesh_<name>.png.
for scene in scenes/mesh/*.ron; do
    name=$(basename "$scene" .ron)
    ./target/release/coordinator --scene "$scene" --out "$out/mesh_$name.png" --width 256 --height 256
done

# The Pixel Stream Editor's solid textures (scenes/pse/), as pse_<name>.png; the
# expression fur and tribble render exactly like fur.png and tribble.png.
for scene in scenes/pse/*.ron; do
    name=$(basename "$scene" .ron)
    case "$name" in fur | tribble) continue ;; esac
    "$bin" --scene "$scene" --out "$out/pse_$name.png" --width 256 --height 256
done

# Figure 12's interactive preset beside the high-quality render.
"$bin" --scene scenes/gilet/holes_r05.ron --out "$out/gilet_holes_r05_interactive.png" --width 256 --height 256 --quality interactive
