#!/usr/bin/env bash
# 200 jobs of 64×64 submitted at once to `coordinator serve` (2 local workers):
# jobs per second and the coordinator's CPU per job.
set -euo pipefail
# Run after `cargo build --release -p coordinator -p worker`; needs curl.
cd "$(dirname "$0")/.."
BIN=${BIN:-target/release}
DATA=$(mktemp -d); OUT=$(mktemp -d)
"$BIN/coordinator" serve --data "$DATA" --listen 127.0.0.1:47123 --local-workers 2 --output-root "$OUT" -q 2>"$OUT/log" &
PID=$!
trap 'kill $PID 2>/dev/null || true; rm -rf "$DATA" "$OUT"' EXIT
for i in $(seq 50); do curl -sf http://127.0.0.1:47123/api/v1/jobs >/dev/null && break; sleep 0.1; done
SCENE=$(python3 -c 'import json,sys; print(json.dumps(open("scenes/noisy_sphere.ron").read()))')
cpu() { awk '{print $14+$15}' /proc/$PID/stat; }
TCK=$(getconf CLK_TCK)
C0=$(cpu); T0=$(date +%s.%N)
for i in $(seq 0 199); do
  printf '{"scene":%s,"scene_name":"noisy_sphere.ron","out":"%s/j%03d.png","width":64,"height":64}' "$SCENE" "$OUT" "$i"
  echo
done | while read -r body; do curl -sf -o /dev/null -X POST -H 'content-type: application/json' --data "$body" http://127.0.0.1:47123/api/v1/jobs; done
T1=$(date +%s.%N)
until [ "$(curl -sf http://127.0.0.1:47123/metrics | awk '/^hypertexture_jobs\{state="done"\}/{print $2}')" = 200 ]; do sleep 0.05; done
T2=$(date +%s.%N); C2=$(cpu)
python3 - "$T0" "$T1" "$T2" "$C0" "$C2" "$TCK" <<'PY'
import sys
t0,t1,t2,c0,c2,tck=map(float,sys.argv[1:])
print(f"submit 200 jobs: {t1-t0:.2f} s; all done after {t2-t0:.2f} s: {200/(t2-t0):.1f} jobs/s; coordinator CPU {(c2-c0)/tck:.2f} s = {(c2-c0)/tck/200*1000:.1f} ms per job")
PY
