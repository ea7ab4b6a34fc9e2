#!/usr/bin/env bash
# The service's tile path: one job of FRAMES (default 30) frames of 64×64 (`noisy_sphere`,
# interactive quality, 1 sample) on `coordinator serve` with 2 local workers
# and --verify 0: tiles stored per second (from the submit to the job done)
# and the coordinator's own CPU per tile (utime+stime from /proc/PID/stat; the
# local workers are other processes). BIN names the directory of the
# `coordinator` and `worker` binaries (default target/release), PORT the port.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${BIN:-target/release}
PORT=${PORT:-47124}
FRAMES=${FRAMES:-30}
DATA=$(mktemp -d); OUT=$(mktemp -d)
# Outputs go to OUT: an output root where the build has them.
ROOTS=()
"$BIN/coordinator" serve --help | grep -q -- --output-root && ROOTS=(--output-root "$OUT")
"$BIN/coordinator" serve --data "$DATA" --listen "127.0.0.1:$PORT" --local-workers 2 --verify 0 "${ROOTS[@]}" -q 2>"$OUT/log" &
PID=$!
trap 'kill $PID 2>/dev/null || true; wait $PID 2>/dev/null || true; rm -rf "$DATA" "$OUT"' EXIT
URL=http://127.0.0.1:$PORT
for i in $(seq 100); do curl -sf "$URL/api/v1/workers" | grep -q '"name"' && [ "$(curl -sf "$URL/api/v1/workers" | grep -o '"name"' | wc -l)" = 2 ] && break; sleep 0.1; done
SCENE=$(python3 -c 'import json; print(json.dumps(open("scenes/noisy_sphere.ron").read()))')
cpu() { awk '{print $14+$15}' "/proc/$PID/stat"; }
TCK=$(getconf CLK_TCK)
C0=$(cpu); T0=$(date +%s.%N)
ID=$(printf '{"scene":%s,"scene_name":"noisy_sphere.ron","out":"%s/f_##.png","width":64,"height":64,"spp":1,"quality":"interactive","frames":[0,%s]}' "$SCENE" "$OUT" "$((FRAMES - 1))" \
  | curl -sf -X POST -H 'content-type: application/json' --data @- "$URL/api/v1/jobs" | python3 -c 'import json,sys; print(json.load(sys.stdin)["id"])')
for i in $(seq 6000); do
  JOB=$(curl -sf "$URL/api/v1/jobs/$ID")
  echo "$JOB" | grep -q '"state":"done"' && break
  sleep 0.02
done
T1=$(date +%s.%N); C1=$(cpu)
UNITS=$(echo "$JOB" | python3 -c 'import json,sys; print(json.load(sys.stdin)["units_total"])')
python3 - "$T0" "$T1" "$C0" "$C1" "$TCK" "$UNITS" <<'PY'
import sys
t0,t1,c0,c1,tck,units=map(float,sys.argv[1:])
print(f"{units:.0f} tiles in {t1-t0:.3f} s: {units/(t1-t0):.0f} tiles/s; coordinator CPU {(c1-c0)/tck:.2f} s = {(c1-c0)/tck/units*1e6:.0f} µs per tile")
PY
