# Sourced by docs/make_compare_report.sh and docs/make_history_report.sh: what both need to make their picture from
# a clean clone of a commit (REV, default HEAD) and not from the work tree, and the throwaway regression both show.
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
REV=${REV:-HEAD}
S=$REPO/.venv/bin/slamreplay
commit=$(git -C "$REPO" rev-parse --verify "$REV^{commit}")
git="git -c user.name=docs -c user.email=docs@localhost"
RANGES_FILE=replay/pipelines/landmark_slam.py  # where D-SLAM reads a scan's ranges

# clone_at DIR [BRANCH]: the repository at $commit in DIR/repo (on a new BRANCH when given)
clone_at() {
    git clone -q "$REPO" "$1/repo"
    git -C "$1/repo" checkout -q ${2:+-b "$2"} "$commit"
}

# use_code_of DIR: slamreplay imported from the clone DIR/repo, before the checkout's editable install
use_code_of() {
    mkdir -p "$1/pkg/slamreplay"
    for p in api replay recorder algorithms; do ln -s "$1/repo/$p" "$1/pkg/slamreplay/$p"; done
    export PYTHONPATH=$1/pkg
}

# degrade_ranges / undo_ranges (in the clone, the current folder): D-SLAM reads every range 3 % long, and back.
# Each fails when its line is not there to edit: a silent no-op would make a picture without the regression.
DEGRADED='r, b, ids = 1.03 * msg.ranges_m[keep]'
degrade_ranges() {
    sed -i 's/r, b, ids = msg.ranges_m\[keep\]/r, b, ids = 1.03 * msg.ranges_m[keep]/' "$RANGES_FILE"
    grep -qF "$DEGRADED" "$RANGES_FILE" || { echo "$RANGES_FILE: no range line to degrade" >&2; exit 1; }
}
undo_ranges() {
    sed -i 's/r, b, ids = 1.03 \* msg.ranges_m\[keep\]/r, b, ids = msg.ranges_m[keep]/' "$RANGES_FILE"
    ! grep -qF "$DEGRADED" "$RANGES_FILE" || { echo "$RANGES_FILE: the degraded line is still there" >&2; exit 1; }
}
