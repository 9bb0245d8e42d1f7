"""kill -9 at random moments of `slamreplay record`, `run`, `suite run` and `serve`: what is left must never look whole.

Each trial starts the command as a process, sends SIGKILL after a seeded random delay (from
just after start-up to past the end of the work), then checks what is on disk:

- record (`sim-landmarks`, a 4-hour simulation written in about 8 s): no ``FILE`` unless the
  command finished; ``FILE.partial`` is either absent (killed before it was opened) or reported
  as truncated by `inspect` (exit 1) and salvaged by `recover` (exit 0 with messages, or exit 2
  "holds no readable message" when the kill came before the first chunk was written; "is empty"
  for a kill between creating the file and writing its header); never an internal error; a second
  `record --out FILE` refuses (exit 2, "already exists").
- run (`odometry` over a 2-hour recording, about 9 s): no ``metrics.json`` or ``run.rrd``
  unless ``manifest.json`` says succeeded; `diff` against the killed run exits 2 saying it is not
  a finished run; a second `run --out DIR` refuses (exit 2, "already exists").
- disk full (a 2 MiB tmpfs, when this process may mount one): `record` and `run` exit 2 saying no
  space is left; no FILE, the .partial is recovered; no run.rrd or metrics.json is left.

- suite run and serve (and the service on a full disk): see ``benchmarks/crash_suite_service.py``.

    .venv/bin/python benchmarks/crash_consistency.py --trials 20 [--commands suite,serve] [--json out.json]

Exit 1 when any trial breaks one of these rules.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import crash_suite_service as cs

SLAMREPLAY = [sys.executable, "-m", "slamreplay.api.cli"]
REPO = Path(__file__).resolve().parents[1]


def cli(*args: str | Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """Run ``slamreplay ARGS`` to completion."""
    return subprocess.run([*SLAMREPLAY, *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=REPO)


def killed(args: list[str | Path], delay_s: float) -> int | None:
    """Start ``slamreplay ARGS``, SIGKILL it after ``delay_s``; its exit code if it finished first, else None."""
    proc = subprocess.Popen([*SLAMREPLAY, *map(str, args)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            cwd=REPO)
    try:
        return proc.wait(delay_s)
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        return None


def one_line_error(p: subprocess.CompletedProcess[str], *needles: str) -> str | None:
    """Why ``p`` is not an exit-2, one-line error holding every needle (None: it is)."""
    if p.returncode != 2 or p.stderr.count("\n") != 1 or not all(n in p.stderr for n in needles):
        return f"exit {p.returncode}: {p.stderr.strip()[:300]!r}"
    return None


def record_trial(work: Path, k: int, delay_s: float) -> dict[str, Any]:
    out = work / f"rec-{k}.mcap"
    partial = out.with_name(out.name + ".partial")
    finished = killed(["record", "sim-landmarks", "--duration-s", "14400", "--seed", str(k), "--out", out, "-q"],
                      delay_s)
    t: dict[str, Any] = {"command": "record", "trial": k, "kill_after_s": round(delay_s, 2), "finished": finished == 0,
                         "problems": []}
    if finished is None and out.exists():
        t["problems"].append("killed, yet FILE exists (a half-written file looks whole)")
    if finished is not None and finished != 0:
        t["problems"].append(f"record failed by itself with exit {finished}")
    if partial.exists():
        t["partial_bytes"] = partial.stat().st_size
        ins = cli("inspect", partial)
        empty = t["partial_bytes"] == 0  # killed between creating the file and writing its header
        if (ins.returncode, "health: truncated" in ins.stdout) != (1, True) and (
                not empty or one_line_error(ins, "is empty (0 bytes)") is not None):
            t["problems"].append(f"inspect of the .partial: exit {ins.returncode}, {ins.stdout[:200]!r}")
        rec = cli("recover", partial, "--out", work / f"rec-{k}-fixed.mcap")
        if empty:
            if (why := one_line_error(rec, "is empty (0 bytes)")) is not None:
                t["problems"].append(f"recover of the empty .partial: {why}")
            t["recovered"] = 0
        elif rec.returncode == 0:
            t["recovered"] = int(rec.stdout.split()[1])
            if cli("inspect", work / f"rec-{k}-fixed.mcap").returncode != 0:
                t["problems"].append("the recovered file is not healthy")
        elif (why := one_line_error(rec, "holds no readable message")) is not None:
            t["problems"].append(f"recover of the .partial: {why}")
        else:
            t["recovered"] = 0
    existed = out.exists() or partial.exists()
    again = cli("record", "sim-landmarks", "--duration-s", "5", "--out", out, "-q")
    if existed and (why := one_line_error(again, "already exists")) is not None:
        t["problems"].append(f"a second record into the same --out: {why}")
    if not existed and again.returncode != 0:  # killed before it wrote anything: nothing is in the way
        t["problems"].append(f"a second record after a kill that left nothing: exit {again.returncode}")
    return t


def run_trial(work: Path, recording: Path, baseline: Path, k: int, delay_s: float) -> dict[str, Any]:
    out = work / f"run-{k}"
    finished = killed(["run", recording, "--pipeline", "odometry", "--out", out, "-q"], delay_s)
    t: dict[str, Any] = {"command": "run", "trial": k, "kill_after_s": round(delay_s, 2), "finished": finished == 0,
                         "problems": []}
    manifest = out / "manifest.json"
    status = json.loads(manifest.read_text())["status"] if manifest.exists() else None
    t["left"] = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if status != "succeeded" and ((out / "metrics.json").exists() or (out / "run.rrd").exists()):
        t["problems"].append(f"killed run left {t['left']} without a succeeded manifest")
    if status != "succeeded" and out.is_dir():
        d = cli("diff", baseline, out)
        if (why := one_line_error(d, str(out))) is not None:
            t["problems"].append(f"diff against the killed run: {why}")
    if out.exists() and any(out.iterdir()):
        again = cli("run", recording, "--pipeline", "odometry", "--out", out, "-q")
        if (why := one_line_error(again, "already exists")) is not None:
            t["problems"].append(f"a second run into the same --out: {why}")
    return t


def disk_full_trials(work: Path, recording: Path) -> list[dict[str, Any]]:
    """record and run into a 2 MiB tmpfs (needs the right to mount; skipped with a note otherwise)."""
    small = work / "small"
    small.mkdir()
    mount = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(small)], capture_output=True,
                           text=True)
    if mount.returncode != 0:
        print(f"disk full: skipped, cannot mount a small tmpfs ({mount.stderr.strip()[:120]})")
        return []
    trials: list[dict[str, Any]] = []
    try:
        out = small / "full.mcap"
        p = cli("record", "sim-landmarks", "--duration-s", "3600", "--seed", "1", "--out", out, "-q")
        t: dict[str, Any] = {"command": "record (disk full)", "trial": 0, "problems": []}
        if (why := one_line_error(p, "no space left on the device", "slamreplay recover")) is not None:
            t["problems"].append(why)
        if out.exists():
            t["problems"].append("FILE exists although the disk filled up")
        rec = cli("recover", out.with_name("full.mcap.partial"), "--out", work / "full-fixed.mcap")
        t["recovered"] = int(rec.stdout.split()[1]) if rec.returncode == 0 else 0
        if rec.returncode != 0:
            t["problems"].append(f"recover of the .partial: exit {rec.returncode}: {rec.stderr.strip()[:200]}")
        trials.append(t)
        for f in small.iterdir():
            f.unlink()
        run_dir = small / "run"
        p = cli("run", recording, "--pipeline", "odometry", "--out", run_dir, "-q")
        t = {"command": "run (disk full)", "trial": 0, "problems": []}
        lines = [ln for ln in p.stderr.splitlines() if ln.startswith("slamreplay")]
        if p.returncode != 2 or len(lines) != 1 or "no space left on the device" not in lines[0]:
            t["problems"].append(f"exit {p.returncode}: {lines}")  # Rerun logs its own sink errors beside ours
        left = sorted(f.name for f in run_dir.iterdir()) if run_dir.exists() else []
        if "run.rrd" in left or "metrics.json" in left:
            t["problems"].append(f"left {left}")
        t["left"] = left
        trials.append(t)
    finally:
        subprocess.run(["umount", str(small)], check=False)
    return trials


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trials", type=int, default=20, help="per command")
    p.add_argument("--seed", type=int, default=18)
    p.add_argument("--json", type=Path)
    p.add_argument("--commands", default="record,run,suite,serve",
                   help="comma-separated, of record, run, suite, serve (default: all)")
    args = p.parse_args(argv)
    commands = set(args.commands.split(","))
    if not commands <= {"record", "run", "suite", "serve"}:
        p.error(f"--commands: unknown {sorted(commands - {'record', 'run', 'suite', 'serve'})}")
    rng = np.random.default_rng(args.seed)
    trials: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="slamreplay-kill-") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        delays = {c: rng.uniform(lo, hi, args.trials) for c, lo, hi in (
            ("record", 0.5, 7.0), ("run", 0.5, 9.0), ("suite", 0.5, 13.0), ("serve", 0.3, 5.0))}
        if "record" in commands:
            for k in range(args.trials):
                trials.append(record_trial(work, k, float(delays["record"][k])))
        if "run" in commands:
            recording = work / "long.mcap"
            cli("record", "sim-landmarks", "--duration-s", "7200", "--seed", "1", "--out", recording, "-q")
            baseline = work / "baseline"
            cli("run", recording, "--pipeline", "odometry", "--out", baseline, "-q")
            for k in range(args.trials):
                trials.append(run_trial(work, recording, baseline, k, float(delays["run"][k])))
            trials.extend(disk_full_trials(work, recording))
        if "suite" in commands or "serve" in commands:
            suite_rec, suite_base = cs.suite_setup(work)
        if "suite" in commands:
            for k in range(args.trials):
                trials.append(cs.suite_trial(work, suite_rec, suite_base, k, float(delays["suite"][k])))
        if "serve" in commands:
            upload = work / "upload.mcap"
            cli("record", "sim-landmarks", "--duration-s", "300", "--seed", "2", "--out", upload, "-q")
            data, rid, base = cs.serve_setup(work, suite_rec)
            for k in range(args.trials):
                trials.append(cs.serve_trial(work, data, rid, base, upload.read_bytes(), k,
                                             float(delays["serve"][k])))
            trials.append(cs.serve_disk_full(work, suite_rec, upload.read_bytes()))
        wall = time.perf_counter() - t0
    for t in trials:
        t.setdefault("finished", False)
        t.setdefault("kill_after_s", None)
    for command in ("record", "run", "suite run", "serve"):
        ts = [t for t in trials if t["command"] == command]
        if not ts:
            continue
        bad = [t for t in ts if t["problems"]]
        extra = ""
        if command == "record":
            rec = [t for t in ts if "partial_bytes" in t]
            extra = (f"; {len(rec)} left a .partial, recovered {sum(1 for t in rec if t.get('recovered'))} with "
                     f"messages, {sum(1 for t in rec if t.get('recovered') == 0)} refused as holding none")
        elif command == "suite run":
            extra = (f"; re-run resumed: {sum(t.get('reused', 0) for t in ts)} cells reused, "
                     f"{sum(t.get('rerun', 0) for t in ts)} run again; results equal to an unkilled run")
        elif command == "serve":
            at_kill = {s: sum(t["at_kill"].get(s, 0) for t in ts) for s in ("queued", "running", "succeeded")}
            ended = {s: sum(t.get("ended", {}).get(s, 0) for t in ts) for s in ("succeeded", "failed", "interrupted")}
            ups = [t["upload"] for t in ts]
            extra = (f"; jobs at the kill {at_kill}, after the restart {ended} "
                     f"({sum(t.get('requeued', 0) for t in ts)} re-queued); slow uploads: "
                     f"{sum(u in (200, 201) for u in ups)} completed, {sum(u not in (200, 201) for u in ups)} cut "
                     f"({sum(t['partial_uploads_left'] for t in ts)} left a temporary file, removed at restart)")
        print(f"{command}: {len(ts)} kill -9 trials, {sum(t['finished'] for t in ts)} finished before the kill, "
              f"{len(ts) - len(bad)} left nothing that looks whole{extra}")
        for t in bad:
            print(f"  trial {t['trial']} (kill after {t['kill_after_s']} s): " + "; ".join(t["problems"]))
    for t in trials:
        if "disk full" in t["command"]:
            state = "ok" if not t["problems"] else "; ".join(t["problems"])
            if "skipped" in t:
                print(f"{t['command']}: skipped, {t['skipped']}")
            elif t["command"] == "serve (disk full)":
                print(f"{t['command']}: {state} (upload {t.get('upload')}; job {t.get('job')})")
            else:
                print(f"{t['command']}: {state}" + (f" ({t['recovered']} messages recovered from the .partial)"
                                                   if "recovered" in t else f" (left {t.get('left')})"))
    print(f"{wall:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(trials, indent=1))
    return 1 if any(t["problems"] for t in trials) else 0


if __name__ == "__main__":
    sys.exit(main())
