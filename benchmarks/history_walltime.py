"""Wall time of ``slamreplay history``: 10 commits x a suite, cold (every cell runs) and warm (all from the store).

A throwaway clone of this repository gets 10 commits (commit 3 reads D-SLAM's ranges 3 % long, commit 6
undoes it, the others add a comment), then ``slamreplay history SUITE --revs first..last --jobs N`` runs
twice into one directory: the first call runs every cell with each commit's own code, the second finds
them all in the store. Each commit's environment is ``SLAMREPLAY_REV_PYTHON`` (this interpreter, over the
commit's worktree) unless ``--build-venvs``: building a virtual environment per commit adds about a minute
each, once. Prints both times and the changes found (expected: commits 3 and 6 only).

    python benchmarks/history_walltime.py [--suite examples/suites/landmarks.toml] [--jobs 2] [--executor local]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEGRADE = ("msg.ranges_m[keep], msg.bearings_rad[keep]", "msg.ranges_m[keep] * 1.03, msg.bearings_rad[keep]")


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=b", "-c", "user.email=b@b", "-C", str(repo), *args],
                          check=True, capture_output=True, text=True).stdout.strip()


def throwaway(root: Path, n: int = 10) -> tuple[Path, list[str]]:
    clone = root / "clone"
    subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
    slam = clone / "replay" / "pipelines" / "landmark_slam.py"
    shas = []
    for i in range(1, n + 1):
        text = slam.read_text()
        if i == 3:
            slam.write_text(text.replace(*DEGRADE))
        elif i == 6:
            slam.write_text(text.replace(DEGRADE[1], DEGRADE[0]))
        else:
            slam.write_text(text + f"# a comment of commit {i}\n")
        git(clone, "commit", "-qam", f"benchmark commit {i}")
        shas.append(git(clone, "rev-parse", "HEAD"))
    return clone, shas


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default=str(REPO / "examples" / "suites" / "landmarks.toml"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--executor", default="local", choices=["local", "ray"])
    ap.add_argument("--build-venvs", action="store_true", help="build each commit's virtual environment")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="history-bench-") as tmp:
        root = Path(tmp)
        clone, shas = throwaway(root)
        env = {**os.environ, "SLAMREPLAY_CACHE": str(root / "cache")}
        if not args.build_venvs:
            env["SLAMREPLAY_REV_PYTHON"] = sys.executable
        cmd = [sys.executable, "-m", "slamreplay.api.cli", "history", str(Path(args.suite).resolve()), "--revs",
               f"{shas[0]}..{shas[-1]}", "--out", str(root / "hist"), "--jobs", str(args.jobs),
               "--executor", args.executor, "-q"]
        times = []
        for _ in range(2):
            tic = time.perf_counter()
            subprocess.run(cmd, cwd=clone, env=env, check=True)
            times.append(time.perf_counter() - tic)
        changes = json.loads((root / "hist" / "changes.json").read_text())
        at = sorted({shas.index(ch["commit"]) + 1 for ch in changes})
        cells = sum(1 for line in (root / "hist" / "history.jsonl").read_text().splitlines() if '"cell"' in line)
        print(f"{len(shas)} commits, {cells} cells, --executor {args.executor} --jobs {args.jobs}: "
              f"cold {times[0]:.1f} s, warm {times[1]:.1f} s; changes at commits {at} "
              f"({len(changes)} metric changes); load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
