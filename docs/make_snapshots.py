"""Render the README's viewer pictures and write their records: each demo pipeline's tabs and a diff, in the
real (headless) Rerun viewer.

Run with `make snapshots` (installs Mesa's Vulkan driver if needed). Pictures are made from a commit, never
from a work tree: the commit (HEAD unless ``--rev``) is exported to a temporary folder and this script runs
again from there, so uncommitted edits in the checkout (yours or anyone's) cannot reach a picture. It runs
`slamreplay demo` there, renders every tab of every run with `slamreplay snapshot` (the loop-closure tab at
the step of a real loop closure), keeps the chosen tabs under ``--out`` as PNGs of at most 300 KB and writes
each picture's record (made by, commit, sha256, the metrics it shows) into docs/images/pictures.json
(docs/pictures.py; `make test-docs` checks them).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = {"api": "api", "replay": "replay", "recorder": "recorder", "algorithms": "algorithms"}
MADE_BY = "make snapshots (docs/make_snapshots.py)"
LOOP = "loop-closure"  # the `at` of a tab drawn at the step of the best loop closure

# (demo run directory, the tabs to keep, picture name, the step shown: end or LOOP)
PICTURES = (
    ("sim-landmarks--dslam", ("Summary", "Filter internals"), "dslam", "end"),
    ("sim-landmarks--ekfslam", ("Filter internals",), "ekfslam", "end"),
    ("sim-landmarks--odometry", ("Summary",), "odometry", "end"),
    ("sim-seabed--ifmi", ("Summary", "Registration", "Pose graph"), "ifmi", "end"),
    ("sim-corridor--topometric", ("Summary",), "topometric", "end"),
    ("sim-corridor--topometric", ("Loop closure",), "topometric", LOOP),
    ("sim-corridor-navigation--topometric-nav", ("Navigation",), "topometric-nav", "end"),
)
DIFF = ("sim-landmarks--dslam", "sim-landmarks--ekfslam", ("Summary", "Metrics A vs B"))
# With --data (the public datasets, as `make demo` finds them): the pictures of docs/real-data.md, each its run's
# Summary tab. (dataset folder, `slamreplay record` arguments, [(run, `slamreplay run` arguments, picture)])
DATASETS = (
    ("mrclam-dataset6", ["mrclam", "{src}", "--robot", "all"],
     [("mrclam-all-dslam", ["--pipeline", "dslam-multi"], "dslam-multi-summary.png")]),
    ("victoria-park-isam", ["victoria-park", "{src}"],
     [("vp-ekfslam", ["--pipeline", "ekfslam"], "victoria-park-ekfslam.png"),
      ("vp-dslam-composite", ["--pipeline", "dslam", "--set", "composite_max_scans=400", "--set",
                              "composite_max_distance_m=20"], "victoria-park-dslam.png"),
      ("vp-slsjf", ["--pipeline", "slsjf"], "victoria-park-slsjf.png")]),
)
MAX_BYTES = 300_000


def save_small(src: Path, dst: Path, width: int = 1280) -> int:
    """Write ``src`` as a PNG of at most MAX_BYTES (scaled down until it fits); its size in bytes."""
    import cv2
    import numpy as np

    img = cv2.imread(str(src))
    while True:
        scale = width / img.shape[1]
        small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else img
        ok, data = cv2.imencode(".png", small, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if not ok:
            raise RuntimeError(f"could not encode {src}")
        if len(data) <= MAX_BYTES or width <= 480:
            dst.write_bytes(np.asarray(data).tobytes())
            return len(data)
        width = int(width * 0.85)


def loop_closure_step(run: Path) -> int:
    """The step of the topo-metric run's most confident loop closure whose accepted candidate is the last one
    drawn at that step (so the candidate view shows it, inliers green); ValueError when the run closed none."""
    from rerun.chunk import RrdReader

    from slamreplay.replay.engine.views import STEP

    lines: list[tuple[int, str]] = []
    for ch in RrdReader(run / "run.rrd").stream():
        if str(ch.entity_path) != "/topo/log" or ch.is_static:
            continue
        rb = ch.to_record_batch()
        lines += [(int(s), " ".join(t) if isinstance(t, list) else str(t))
                  for s, t in zip(rb.column(STEP).to_pylist(), rb.column("TextLog:text").to_pylist(), strict=True)]
    lines.sort(key=lambda row: row[0])  # stable: the log order within a step is kept
    best: tuple[float, int, int] | None = None  # (-probability, -inliers, step)
    for step in sorted({s for s, _ in lines}):
        at = [t for s, t in lines if s == step]
        closure = next((re.search(r"LOOP CLOSURE with location (\d+) \(p=([\d.]+), (\d+) inliers", t) for t in at
                        if "LOOP CLOSURE" in t), None)
        candidates = [re.search(r"candidate location (\d+)", t) for t in at if "candidate location" in t]
        if closure is None or not candidates or candidates[-1] is None or candidates[-1][1] != closure[1]:
            continue
        key = (-float(closure[2]), -int(closure[3]), step)
        best = key if best is None or key < best else best
    if best is None:
        raise ValueError(f"{run} closed no loop: no step to show the loop-closure tab at")
    return best[2]


def run_label(name: str) -> str:
    return name.lower().replace(" ", "-")


def render(demo: Path, out: Path, size: tuple[int, int], commit: str, records_path: Path) -> int:
    """Render every picture from the finished demo in ``demo`` into ``out`` and record each (the inner pass)."""
    sys.path.insert(0, str(REPO / "docs"))
    import pictures

    from slamreplay.replay.runs.diff_view import write_comparison_rrd
    from slamreplay.replay.tools.snapshot import snapshot

    def metrics(*runs: str) -> dict[str, float]:
        out: dict[str, float] = {}
        for run in runs:
            doc = json.loads((demo / run / "metrics.json").read_text())["metrics"]
            out.update({f"{run}/{k}": float(v["value"]) for k, v in doc.items()})
        return out

    records = pictures.load(records_path)
    out.mkdir(parents=True, exist_ok=True)

    def keep(src: Path, name: str, shows: dict[str, float], note: str = "") -> None:
        dst = out / name
        size_b = save_small(src, dst)
        records[name] = pictures.record(dst, MADE_BY, commit, "demo", shows, note)
        print(f"{name}: {size_b / 1000:.0f} kB")

    with tempfile.TemporaryDirectory() as tmp:
        for i, (run, tabs, name, at) in enumerate(PICTURES):
            step: str | int = loop_closure_step(demo / run) if at == LOOP else at
            for shot in snapshot(demo / run, Path(tmp) / f"{i}-{name}", size=size, at=step):
                if shot.tab in tabs:
                    # a Summary tab shows the run's metrics table; the other tabs show series, images, maps
                    shows = metrics(run) if shot.tab == "Summary" else {}
                    note = f"at step {step}: a loop closure" if at == LOOP else ""
                    keep(shot.path, f"{name}-{run_label(shot.tab)}.png", shows, note)
        a, b, tabs = DIFF
        cmp = Path(tmp) / "diff.rrd"
        write_comparison_rrd(demo / a, demo / b, cmp)  # titled demo/RUN (diff_view.run_name): no machine path
        for shot in snapshot(cmp, Path(tmp) / "diff", size=size):
            if shot.tab in tabs:
                keep(shot.path, f"diff-{run_label(shot.tab)}.png", metrics(a, b) if shot.tab == "Summary" else {})
    pictures.save(records, records_path)
    print(f"records: {records_path}")
    return 0


def render_datasets(data: Path, out: Path, size: tuple[int, int], commit: str, records_path: Path) -> int:
    """The dataset pictures (DATASETS) from runs made here of the public datasets in ``data``; each recorded with
    the metrics its Summary tab shows (not checked against the demo: `make test-docs` has no datasets)."""
    sys.path.insert(0, str(REPO / "docs"))
    import pictures

    from slamreplay.replay.tools.snapshot import snapshot

    cli = [sys.executable, "-m", "slamreplay.api.cli"]
    records = pictures.load(records_path)
    for folder, record_args, runs in DATASETS:
        src = data / folder
        if not src.is_dir():
            print(f"{src}: not there, its pictures are kept as they are")
            continue
        recording = Path.cwd() / f"{folder}.mcap"
        subprocess.run([*cli, "record", *[a.format(src=src) for a in record_args], "--out", str(recording)],
                       check=True, stdout=subprocess.DEVNULL)
        for run, run_args, name in runs:
            run_dir = Path.cwd() / run
            subprocess.run([*cli, "run", str(recording), *run_args, "--out", str(run_dir), "--quiet"], check=True,
                           stdout=subprocess.DEVNULL)
            with tempfile.TemporaryDirectory() as tmp:
                shot = next(s for s in snapshot(run_dir, Path(tmp), size=size) if s.tab == "Summary")
                size_b = save_small(shot.path, out / name)
            doc = json.loads((run_dir / "metrics.json").read_text())["metrics"]
            how = f"{folder}: slamreplay record {record_args[0]}, run {' '.join(run_args)}"
            records[name] = pictures.record(out / name, f"{MADE_BY} with --data", commit, how,
                                            {f"{run}/{k}": float(v["value"]) for k, v in doc.items()})
            print(f"{name}: {size_b / 1000:.0f} kB")
    pictures.save(records, records_path)
    return 0


# The web page's pictures the docs link, written by the browser tests that take them (SLAMREPLAY_README_IMAGES)
WEB_TESTS = ("tests/web/test_pages.py", "tests/web/test_runs_view.py", "tests/web/test_live_job.py",
             "tests/web/test_browser.py")
WEB_METRICS = {  # what each shows, by name (values: the tests' own runs, not the demo's)
    "web-runs": ("ape_rmse_m", "rpe_step_trans_rmse_m"),
    "web-groups-laptop": ("ape_rmse_m", "landmark_rmse_m", "landmark_nees_mean"),
    "web-grouped": ("ape_rmse_m", "landmark_rmse_m", "landmark_nees_mean"),
    "web-scatter-laptop": ("landmark_rmse_m",),
    "web-group-chart-phone": ("ape_rmse_m",),
    "web-compare-nees": ("robot_nees_mean",),
    "web-compare": ("ape_rmse_m", "ape_rot_rmse_deg", "ape_se2_rmse_m", "path_length_m", "poses_scored",
                    "robot_final_error_m", "robot_max_error_m", "rpe_m_rot_rmse_deg", "rpe_m_trans_rmse_m",
                    "rpe_step_rot_rmse_deg", "rpe_step_trans_rmse_m"),
}


def render_web(out: Path, commit: str, records_path: Path) -> int:
    """The web page's pictures the docs link, from the browser tests of this export (chromium, Playwright)."""
    sys.path.insert(0, str(REPO / "docs"))
    import pictures

    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "SLAMREPLAY_README_IMAGES": tmp, "SLAMREPLAY_BROWSER_SHOTS": str(Path(tmp) / "shots"),
               "PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD": "1"}
        status = subprocess.run([sys.executable, "-m", "pytest", "-q", "-m", "browser", "-p", "no:cacheprovider",
                                 *WEB_TESTS], cwd=REPO, env=env).returncode
        if status != 0:
            return status
        records = pictures.load(records_path)
        linked = pictures.linked()  # this export's README.md and docs/*.md: the commit's own links
        for png in sorted(Path(tmp).glob("web-*.png")):
            if png.name not in linked:
                continue
            shutil.copyfile(png, out / png.name)
            shows = next((names for key, names in WEB_METRICS.items() if png.name.startswith(key)), ())
            records[png.name] = pictures.record(out / png.name, f"{MADE_BY} --what web ({', '.join(WEB_TESTS)})",
                                                commit, "the browser tests' own runs",
                                                {f"tests-web/{name}": None for name in shows})
            print(f"{png.name}: {png.stat().st_size / 1000:.0f} kB")
        pictures.save(records, records_path)
    return 0


def export(rev: str, dst: Path) -> tuple[str, Path]:
    """(full commit id, package root) of ``rev`` exported to ``dst``: its tracked files and a ``slamreplay``
    package folder of links, which PYTHONPATH puts before the checkout's editable install."""
    commit = subprocess.run(["git", "rev-parse", "--verify", f"{rev}^{{commit}}"], cwd=REPO, capture_output=True,
                            text=True, check=True).stdout.strip()
    src = dst / "src"
    src.mkdir(parents=True)
    archive = subprocess.run(["git", "archive", commit], cwd=REPO, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
    pkg = dst / "pkg" / "slamreplay"
    pkg.mkdir(parents=True)
    for name, folder in PACKAGES.items():
        (pkg / name).symlink_to(src / folder)
    return commit, dst / "pkg"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "images")
    ap.add_argument("--rev", default="HEAD", help="the commit to make the pictures from (default HEAD)")
    ap.add_argument("--size", default="1600x900", help="viewer size (default: 1600x900)")
    ap.add_argument("--data", type=Path, default=None,
                    help="the public datasets (../shared/data): the pictures of docs/real-data.md too (7 more minutes)")
    ap.add_argument("--what", choices=("viewer", "web", "all"), default="viewer",
                    help="the viewer's pictures (default), the web page's (browser tests: chromium, Playwright), both")
    ap.add_argument("--records", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--commit", default=None, help=argparse.SUPPRESS)  # set by the outer pass: run from an export
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    if args.commit is None:  # the outer pass: export the commit, run this script from there
        with tempfile.TemporaryDirectory(prefix="slamreplay-snapshots-") as tmp:
            commit, pkg = export(args.rev, Path(tmp))
            print(f"make snapshots: from commit {commit[:12]} (exported; the work tree is not used)")
            env = {**os.environ, "PYTHONPATH": str(pkg)}
            data = ["--data", str(args.data.resolve())] if args.data is not None else []
            data += ["--what", args.what]
            return subprocess.run([sys.executable, str(Path(tmp) / "src" / "docs" / "make_snapshots.py"),
                                   "--out", str(args.out.resolve()), "--size", args.size, "--commit", commit,
                                   "--records", str((REPO / "docs" / "images" / "pictures.json").resolve()), *data],
                                  env=env, cwd=tmp).returncode
    status = 0
    if args.what in ("viewer", "all"):
        from slamreplay.api.cli.demo import run_demo

        demo = Path.cwd() / "demo"
        if run_demo(demo, None, quiet=True) != 0:
            return 1
        status = render(demo, args.out, (w, h), args.commit, args.records)
        if status == 0 and args.data is not None:
            status = render_datasets(args.data, args.out, (w, h), args.commit, args.records)
    if status == 0 and args.what in ("web", "all"):
        status = render_web(args.out, args.commit, args.records)
    return status


if __name__ == "__main__":
    sys.exit(main())
