#!/bin/bash
# The history report's picture (docs/images/history_report.png) and its record (docs/pictures.py): a throwaway
# history of 10 commits on top of a commit (REV, default HEAD) in a clean clone, whose commit 3 reads D-SLAM's
# ranges 3 % long and commit 6 undoes it, the others touching comments only; `slamreplay history` over them with
# examples/suites/landmarks.toml, drawn by headless chromium. The first run builds the revisions' shared
# environment (pip, minutes); then about 5 minutes on 2 cores. Run from the repository: bash docs/make_history_report.sh
set -euo pipefail
source "$(dirname "$0")/clone_at_rev.sh"
tmp=$(mktemp -d /tmp/slamreplay-history-report-XXXXXX)
trap 'rm -rf "$tmp"' EXIT
clone_at "$tmp" history-example
cd "$tmp/repo"
file=$RANGES_FILE
for i in 1 2 3 4 5 6 7 8 9; do
    if [ $i = 3 ]; then
        degrade_ranges; msg="degrade: ranges read 3% long"
    elif [ $i = 6 ]; then
        undo_ranges; msg="undo the range scale"
    else
        echo "# history example: comment $i" >> $file; msg="comment $i"
    fi
    $git commit -qam "$msg"
done
use_code_of "$tmp"  # the clone's code drives the history
$S history examples/suites/landmarks.toml --revs "$commit..history-example" --out ../h --jobs 2 \
    --markdown ../summary.md --quiet 2> ../history.err || { cat ../history.err; exit 1; }
chromium --headless --no-sandbox --disable-gpu --hide-scrollbars --window-size=1100,2200 \
    --screenshot="$REPO/docs/images/history_report.png" "file://$tmp/h/index.html" 2> /dev/null
"$REPO/.venv/bin/python" - "$REPO" "$commit" "$tmp/summary.md" <<'PY'
import re, sys
from pathlib import Path
sys.path.insert(0, f"{sys.argv[1]}/docs")
import pictures
from slamreplay.replay.metric_registry import METRICS
text = Path(sys.argv[3]).read_text()
names = sorted({w for w in re.findall(r"[a-z][a-z0-9_]+", text) if w in METRICS})
records = pictures.load()
png = pictures.IMAGES / "history_report.png"
records[png.name] = pictures.record(png, "bash docs/make_history_report.sh", sys.argv[2],
                                    "examples/suites/landmarks.toml over 10 throwaway commits on top of the commit "
                                    "(3: D-SLAM's ranges read 3 % long, 6: undone)",
                                    {f"landmarks/dslam/default/{n}": None for n in names})
pictures.save(records)
print(f"history_report.png: {len(names)} metrics named in the changes, from {sys.argv[2][:12]}")
PY
