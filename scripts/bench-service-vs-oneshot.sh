#!/usr/bin/env bash
# The fur at 512² (the scene's size): the service's frame time against the
# one-shot command's, alternating, both with 2 local workers.
set -euo pipefail
# Run after `cargo build --release -p coordinator -p worker`; needs curl.
cd "$(dirname "$0")/.."
BIN=${BIN:-target/release}; N=${N:-7}
DATA=$(mktemp -d); OUT=$(mktemp -d)
"$BIN/coordinator" serve --data "$DATA" --listen 127.0.0.1:47124 --local-workers 2 --output-root "$OUT" 2>"$OUT/log" &
PID=$!
trap 'kill $PID 2>/dev/null || true; rm -rf "$DATA" "$OUT"' EXIT
for i in $(seq 50); do curl -sf http://127.0.0.1:47124/api/v1/jobs >/dev/null && break; sleep 0.1; done
sleep 1
for r in $(seq $N); do
  "$BIN/coordinator" --scene scenes/fur.ron --out "$OUT/one.png" 2>&1 | sed -n 's/.*with the farm in \([0-9.]*\) s.*/oneshot \1/p'
  id=$("$BIN/coordinator" submit --server http://127.0.0.1:47124 scenes/fur.ron --out "$OUT/svc$r.png")
  "$BIN/coordinator" wait --server http://127.0.0.1:47124 "$id" >/dev/null
  sed -n "s/.*job $id: frame 0 in \([0-9.]*\) s.*/service \1/p" "$OUT/log"
  cmp "$OUT/one.png" "$OUT/svc$r.png"
done
