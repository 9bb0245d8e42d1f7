#!/usr/bin/env bash
# The same cells (recording, pipeline, seed) run under two environments (two Pythons, so other
# numpy/scipy/BLAS builds) must pass `slamreplay diff`: exit 0, numerical noise within the
# default tolerances. Usage: .ci/cross-python-diff.sh VENV_A VENV_B [WORKDIR]
set -euo pipefail
a=$1 b=$2
work=${3:-$(mktemp -d)}
mkdir -p "$work"
"$a/bin/slamreplay" record sim-landmarks --out "$work/sim.mcap" --seed 1 --duration-s 300 -q
"$a/bin/slamreplay" record sim-seabed --out "$work/seabed.mcap" --seed 1 -q
"$a/bin/slamreplay" record sim-corridor --out "$work/corridor.mcap" --seed 1 --camera-rate-hz 2.5 -q
status=0
for cell in sim:odometry sim:dslam sim:ekfslam seabed:ifmi corridor:topometric; do
    rec=${cell%%:*} pipeline=${cell#*:}
    for venv in "$a" "$b"; do
        "$venv/bin/slamreplay" run "$work/$rec.mcap" --pipeline "$pipeline" --seed 1 -q \
            --out "$work/runs/$(basename "$venv")/$rec-$pipeline"
    done
    echo "== $rec $pipeline: $(basename "$a") -> $(basename "$b")"
    "$a/bin/slamreplay" diff "$work/runs/$(basename "$a")/$rec-$pipeline" "$work/runs/$(basename "$b")/$rec-$pipeline" \
        | grep -E "python|numpy|scipy|rerun|WORSE|changed  |Result" || true
    "$a/bin/slamreplay" diff "$work/runs/$(basename "$a")/$rec-$pipeline" "$work/runs/$(basename "$b")/$rec-$pipeline" \
        > /dev/null || { echo "FAILED: $rec through $pipeline differs beyond the default tolerances"; status=1; }
done
exit $status
