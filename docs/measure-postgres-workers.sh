#!/usr/bin/env bash
# Jobs per minute with 1, 2 and 4 `lungmotion worker` processes on one PostgreSQL (the bundled
# phantom, 12 mm, 2 phases, N jobs, default 8), as in the README ("Running it across machines").
# Run as root (initdb and pg_ctl run as the postgres user) after a build of the binary.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
BIN=${BIN:-$ROOT/target/debug/lungmotion}
PGBIN=$(ls -d /usr/lib/postgresql/*/bin | tail -1)
D=$(mktemp -d /tmp/lm-measure.XXXX); chown postgres $D
PORT=55439
echo secret > $D/pw; chown postgres $D/pw
runuser -u postgres -- $PGBIN/initdb -D $D/pg -U lm --pwfile=$D/pw -A scram-sha-256 --no-sync >/dev/null
runuser -u postgres -- $PGBIN/pg_ctl -D $D/pg -o "-p $PORT -k $D -c listen_addresses=127.0.0.1 -c fsync=off" -l $D/pg.log -w start >/dev/null
PGPASSWORD=secret $PGBIN/psql -h 127.0.0.1 -p $PORT -U lm -d postgres -qc "CREATE DATABASE lungmotion"
export LUNGMOTION_POSTGRES_URL="postgres://lm:secret@127.0.0.1:$PORT/lungmotion"
export LUNGMOTION_LOG=warn
$BIN serve --data-dir $D/data --listen 127.0.0.1:18089 > $D/serve.out 2> $D/serve.log &
SERVE=$!
trap 'kill $SERVE 2>/dev/null; for p in $(jobs -p); do kill -9 $p 2>/dev/null; done; runuser -u postgres -- $PGBIN/pg_ctl -D $D/pg -m immediate stop >/dev/null' EXIT
until grep -q listening $D/serve.out; do sleep 0.2; done
API=http://127.0.0.1:18089
SCAN=$(curl -s -X POST --data-binary @$ROOT/sample-volumes/phantom-ct.nii.gz $API/v1/scans | python3 -c 'import json,sys; print(json.load(sys.stdin)["scan_id"])')
REQ=$(python3 - <<'PY'
import json, math
t=[i*0.1 for i in range(81)]; v=[250*(1-math.cos(2*math.pi*x/4)) for x in t]
print(json.dumps({"trace":{"time_s":t,"volume_ml":v},"element_size_mm":12,"motion":{"instants":{"kind":"phases","count":2}},"outputs":{"quicklooks":False}}))
PY
)
N=${N:-8}
for W in 1 2 4; do
  PIDS=()
  for i in $(seq $W); do
    $BIN worker --data-dir $D/data --workers 1 > $D/w$W-$i.out 2> $D/w$W-$i.log & PIDS+=($!)
  done
  for i in $(seq $W); do until grep -q "taking jobs" $D/w$W-$i.out; do sleep 0.2; done; done
  START=$(date +%s.%N)
  IDS=()
  for j in $(seq $N); do
    IDS+=($(curl -s -X POST -H 'content-type: application/json' --data "$REQ" $API/v1/scans/$SCAN/simulations | python3 -c 'import json,sys; print(json.load(sys.stdin)["job_id"])'))
  done
  for id in "${IDS[@]}"; do
    until curl -s $API/v1/jobs/$id | grep -q '"state":"done"'; do sleep 0.2; done
  done
  END=$(date +%s.%N)
  python3 -c "d=$END-$START; print(f'workers={$W} jobs={$N} seconds={d:.1f} jobs_per_minute={$N*60/d:.1f}')"
  for p in "${PIDS[@]}"; do kill $p; wait $p 2>/dev/null || true; done
done
