#!/bin/bash
# docs/images/compare_report.png and its record (docs/pictures.py): the README's throwaway regression, made from a
# clean clone of a commit (REV, default HEAD): `suite run` of examples/suites/landmarks.toml there (A), the same
# after a commit that reads D-SLAM's ranges 3 % long (B), `slamreplay compare a b --report`, drawn by headless
# chromium. About 2 minutes on 2 cores. Run from the repository: bash docs/make_compare_report.sh
set -euo pipefail
source "$(dirname "$0")/clone_at_rev.sh"
tmp=$(mktemp -d /tmp/slamreplay-compare-report-XXXXXX)
trap 'rm -rf "$tmp"' EXIT
clone_at "$tmp"
use_code_of "$tmp"
cd "$tmp/repo"
$S suite run examples/suites/landmarks.toml --out "$tmp/a" --jobs 2 --quiet > /dev/null
degrade_ranges
$git commit -qam "throwaway: D-SLAM ranges scaled by 1.03"
$S suite run examples/suites/landmarks.toml --out "$tmp/b" --jobs 2 --quiet > /dev/null
cd "$tmp"  # the report names the results folders as given: a and b, no machine path
$S compare a b --report report.html --json > report.json || test $? -eq 1
chromium --headless --no-sandbox --disable-gpu --hide-scrollbars --window-size=1200,1000 \
    --screenshot="$REPO/docs/images/compare_report.png" "file://$tmp/report.html" 2> /dev/null
"$REPO/.venv/bin/python" - "$REPO" "$commit" "$tmp/report.json" <<'PY'
import json, sys
from pathlib import Path
sys.path.insert(0, f"{sys.argv[1]}/docs")
import pictures
doc = json.loads(Path(sys.argv[3]).read_text())
shown = {}
for row in doc["results"]:
    if row["verdict"] == "regression":
        cell = f"{row['recording']}/{row['pipeline']}/{row['variant']}"
        shown[f"A {cell}/{row['metric']}"] = row["a_mean"]
        shown[f"B {cell}/{row['metric']}"] = row["b_mean"]
records = pictures.load()
png = pictures.IMAGES / "compare_report.png"
records[png.name] = pictures.record(png, "bash docs/make_compare_report.sh", sys.argv[2], "examples/suites/"
                                    "landmarks.toml, seeds 1-3: the commit (A) against it with D-SLAM's ranges read "
                                    "3 % long (B)", shown)
pictures.save(records)
print(f"compare_report.png: {len(shown) // 2} regressions shown, from {sys.argv[2][:12]}")
PY
