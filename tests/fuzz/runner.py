"""The running half of the fuzz harness: mutants through `inspect`, `run` and `recover`, in-process.

Each worker is a ``spawn``-ed process that imports slamreplay once, warms up on the base
recordings, then limits its own address space (``RLIMIT_AS``: its warm size plus
``memory_headroom`` bytes, far more than any honest read of a < 100 KB file needs) and
takes mutants one by one. Every command is the CLI's ``main([...])`` under a
``signal.alarm`` time limit; the parent also kills a worker that stops answering. Outcomes:

- ``ok``: exit 0; ``clean``: exit 1 (``inspect`` found damage) or 2 (an error on one line);
- ``internal``: exit 3 (an exception the code did not expect), an exception out of ``main``
  or a worker that died; ``hang``: over the time limit;
- ``wrong``: a ``recover`` that exits 0 but whose output is not a healthy recording holding
  the messages it says it kept, or that kept none (it must exit 2 then).
"""

from __future__ import annotations

import contextlib
import io
import json
import multiprocessing as mp
import multiprocessing.connection as mpc
import os
import re
import resource
import shutil
import signal
import tempfile
import time
import traceback
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

COMMANDS = ("inspect", "run", "recover")
# Each run leaves some address space reserved (Rerun's sink threads and allocator arenas), so a worker
# is replaced after this many mutants: the limit keeps measuring the mutant, not the worker's history.
RECYCLE = 100
OUTCOMES = ("ok", "clean", "internal", "hang", "wrong")


class _Timeout(BaseException):
    """Raised by the alarm; a BaseException so that no `except Exception` in the code swallows it."""


def _on_alarm(signum: int, frame: Any) -> None:
    raise _Timeout


@contextlib.contextmanager
def _fd2_captured() -> Iterator[io.StringIO]:
    """What C libraries (libpng, zstd...) write straight to file descriptor 2 while the block runs."""
    got = io.StringIO()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield got
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            got.write(tmp.read().decode(errors="replace"))


def _call(argv: list[str], time_limit_s: int) -> tuple[str, int | None, str, str]:
    """(outcome, exit code, stdout, stderr) of ``slamreplay ARGV`` run in this process; stderr holds what
    Python printed and what C code wrote to file descriptor 2, as a user's terminal would show both."""
    from slamreplay.api.cli.command import main

    out, err = io.StringIO(), io.StringIO()
    rc: int | None = None
    outcome = ""
    with _fd2_captured() as raw:
        signal.alarm(time_limit_s)
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                rc = main(argv)
        except _Timeout:
            outcome = "hang"
        except (Exception, SystemExit, MemoryError) as exc:  # noqa: BLE001 -- anything out of main() is a finding
            outcome = "internal"
            err.write("".join(traceback.format_exception(exc)))
        finally:
            signal.alarm(0)
    stderr = raw.getvalue() + err.getvalue()
    if not outcome:
        outcome = "ok" if rc == 0 else "clean" if rc in (1, 2) else "internal"
    return outcome, rc, out.getvalue(), stderr


def _check_recovered(stdout: str, out: Path) -> str | None:
    """Why a recover that exited 0 did not tell the truth (None: it did)."""
    from slamreplay.replay.engine.reader import RecordingReader
    from slamreplay.replay.tools.inspect import inspect_recording

    kept = re.search(r"recovered (\d+) messages", stdout)
    if kept is None:
        return f"recover printed no message count: {stdout.strip()!r}"
    if int(kept.group(1)) == 0:
        return "recover exited 0 having kept no message"
    report = inspect_recording(out)
    if report["health"] != "ok":
        return f"the recovered file is {report['health']}: {report['problems']}"
    read = sum(1 for _ in RecordingReader(out).raw([t.file_topic for t in RecordingReader(out).info.topics]))
    if read != int(kept.group(1)) or report["message_count"] != read:
        return f"recover says {kept.group(1)} messages kept, the file holds {read} ({report['message_count']} counted)"
    return None


def check_mutant(path: Path, pipeline: str, work: Path, time_limit_s: int) -> dict[str, Any]:
    """Run one mutant file through the three commands; outcome, exit code and first error line of each."""
    result: dict[str, Any] = {}
    for command in COMMANDS:
        out = work / f"{command}.out"
        if command == "inspect":
            argv = ["inspect", str(path)]
        elif command == "run":
            argv = ["run", str(path), "--pipeline", pipeline, "--out", str(out), "--quiet"]
        else:
            argv = ["recover", str(path), "--out", str(out)]
        outcome, rc, stdout, stderr = _call(argv, time_limit_s)
        entry: dict[str, Any] = {"outcome": outcome, "exit": rc}
        lines = stderr.strip().splitlines()
        if outcome == "clean" and rc == 2:
            entry["error"] = lines[0][:400] if lines else ""
            if len(lines) != 1:
                entry.update(outcome="wrong", why=f"error not on one line: {stderr[:400]!r}")
        elif outcome == "internal":
            entry["error"] = (lines[-1] if lines else "")[:400]
            if rc == 3:  # again with --debug, for the traceback
                debug = ["--debug", *argv]
                if "--out" in debug:
                    debug[debug.index("--out") + 1] += ".debug"
                entry["traceback"] = _call(debug, time_limit_s)[3][-3000:]
            else:
                entry["traceback"] = stderr[-3000:]
        elif outcome == "ok" and command == "recover":
            try:
                why = _check_recovered(stdout, out)
            except Exception as exc:  # noqa: BLE001 -- an unreadable recovered file is a finding too
                why = f"the recovered file cannot be read: {type(exc).__name__}: {exc}"
            if why is not None:
                entry.update(outcome="wrong", why=why)
        elif outcome == "clean" and rc == 1 and command == "inspect":
            entry["error"] = next((ln.strip() for ln in stdout.splitlines() if "problem:" in ln), "")[:400]
        if entry["outcome"] in ("ok", "clean") and rc != 2 and stderr.strip():
            entry.update(outcome="wrong", why=f"exit {rc} with output on stderr: {stderr[:400]!r}")
        result[command] = entry
        for leftover in work.iterdir():
            if leftover.is_dir():
                shutil.rmtree(leftover, ignore_errors=True)
            else:
                leftover.unlink(missing_ok=True)
    return result


def _worker(conn: mpc.Connection, bases: dict[str, str], work: str, memory_headroom: int) -> None:
    """Warm up, limit the address space, then answer (kind, seed, index, time limit) tasks until None."""
    from tests.fuzz.mutate import RUN_PIPELINE, mutant

    signal.signal(signal.SIGALRM, _on_alarm)
    root = Path(work)
    root.mkdir(parents=True, exist_ok=True)
    data = {kind: Path(p).read_bytes() for kind, p in bases.items()}
    scratch = root / "scratch"
    scratch.mkdir(exist_ok=True)
    for kind, p in bases.items():  # warm: every import and lazy initialisation happens before the limit
        check_mutant(Path(p), RUN_PIPELINE[kind], scratch, 60)
    with open("/proc/self/status") as f:
        peak = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmPeak"))
    limit = peak + memory_headroom
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    conn.send({"ready": True, "limit": limit})
    done = 0
    while done < RECYCLE:
        task = conn.recv()
        if task is None:
            return
        kind, seed, index, op, time_limit_s, keep = task
        m = mutant(data[kind], seed, index, op)
        path = root / f"{kind}-{seed}-{index}.mcap"
        path.write_bytes(m.data)
        t0 = time.perf_counter()
        try:
            result = check_mutant(path, RUN_PIPELINE[kind], scratch, time_limit_s)
        finally:
            signal.alarm(0)
        bad = any(r["outcome"] not in ("ok", "clean") for r in result.values())
        if bad and keep:
            shutil.copy(path, Path(keep) / path.name)
        path.unlink(missing_ok=True)
        done += 1
        conn.send({"kind": kind, "seed": seed, "index": index, "recipe": m.recipe, "size": len(m.data),
                   "seconds": round(time.perf_counter() - t0, 3), "results": result})


@dataclass
class Campaign:
    """Every mutant's outcomes; ``table()`` counts them per kind and command."""

    results: list[dict[str, Any]] = field(default_factory=list)

    def counts(self, by: str = "kind") -> dict[tuple[str, str], Counter[str]]:
        """Outcomes per (kind, command), or per (operator, command) with ``by="op"``."""
        table: dict[tuple[str, str], Counter[str]] = {}
        for r in self.results:
            key = r["kind"] if by == "kind" else str(r["recipe"].get("op", "?"))
            for command, entry in r["results"].items():
                table.setdefault((key, command), Counter())[entry["outcome"]] += 1
        return table

    def findings(self) -> list[dict[str, Any]]:
        """Mutants with an internal error, a hang or a wrong recover."""
        return [r for r in self.results if any(e["outcome"] not in ("ok", "clean") for e in r["results"].values())]

    def findings_text(self, label: Callable[[dict[str, Any]], str]) -> str:
        """Each finding's command, outcome, reason, recipe and the end of its traceback; ``label(row)`` names it."""
        out = []
        for r in self.findings():
            for command, e in r["results"].items():
                if e["outcome"] not in ("ok", "clean"):
                    out.append(f"\n{label(r)} seed {r['seed']} index {r['index']} {command}: {e['outcome']}: "
                               f"{e.get('why') or e.get('error')}\n  recipe {json.dumps(r['recipe'])[:300]}")
                    if e.get("traceback"):
                        out.append("  " + "\n  ".join(e["traceback"].strip().splitlines()[-6:]))
        return "\n".join(out)

    def table(self, by: str = "kind") -> str:
        rows = [f"| {by} | command | mutants | {' | '.join(OUTCOMES)} |", "|" + " --- |" * (3 + len(OUTCOMES))]
        totals: dict[str, Counter[str]] = {}
        for (kind, command), c in sorted(self.counts(by).items()):
            rows.append(f"| {kind} | {command} | {sum(c.values())} | " + " | ".join(str(c[o]) for o in OUTCOMES) + " |")
            totals.setdefault(command, Counter()).update(c)
        for command, c in sorted(totals.items()):
            rows.append(f"| **all** | {command} | {sum(c.values())} | " + " | ".join(str(c[o]) for o in OUTCOMES)
                        + " |")
        return "\n".join(rows)


def run_campaign(bases: dict[str, Path], tasks: list[tuple[Any, ...]], work: Path, *, workers: int = 2,
                 time_limit_s: int = 30, memory_headroom: int = 2 << 30, keep: Path | None = None,
                 progress: Any = None) -> Campaign:
    """Run (kind, seed, index) or (kind, seed, index, operator) mutants over ``workers`` processes; a worker
    that stops answering within ``2 * time_limit_s + 10`` seconds per mutant is killed and replaced (the
    mutant counts as a hang), one that dies counts as an internal error."""
    ctx = mp.get_context("spawn")
    campaign = Campaign()
    pending = [(*t, None)[:4] for t in reversed(tasks)]  # (kind, seed, index, forced operator or None)
    slots: list[dict[str, Any]] = []

    def spawn(n: int) -> dict[str, Any]:
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_worker, args=(child, {k: str(v) for k, v in bases.items()},
                                                 str(work / f"w{n}"), memory_headroom), daemon=True)
        proc.start()
        child.close()
        ready = parent.recv() if parent.poll(300) else None
        if not ready:
            raise RuntimeError(f"fuzz worker {n} did not start")
        return {"n": n, "proc": proc, "conn": parent, "task": None, "since": 0.0, "done": 0}

    def dead(slot: dict[str, Any], outcome: str, why: str) -> None:
        kind, seed, index, op = slot["task"]
        campaign.results.append({"kind": kind, "seed": seed, "index": index, "recipe": {"op": op} if op else {},
                                 "size": 0, "seconds": 0,
                                 "results": {c: {"outcome": outcome, "exit": None, "error": why} for c in COMMANDS}})
        slot["proc"].kill()
        slot["proc"].join()
        slots[slots.index(slot)] = spawn(slot["n"])

    try:
        slots.extend(spawn(n) for n in range(workers))
        while pending or any(s["task"] for s in slots):
            for slot in slots:
                if slot["task"] is None and pending:
                    slot["task"] = pending.pop()
                    slot["since"] = time.monotonic()
                    slot["conn"].send((*slot["task"], time_limit_s, str(keep) if keep else None))
            busy = [s for s in slots if s["task"]]
            ready = mpc.wait([s["conn"] for s in busy], timeout=1.0)
            for slot in list(busy):
                if slot["conn"] in ready:
                    try:
                        campaign.results.append(slot["conn"].recv())
                    except EOFError:
                        dead(slot, "internal", f"worker died (exit {slot['proc'].exitcode})")
                        continue
                    slot["task"] = None
                    slot["done"] += 1
                    if slot["done"] >= RECYCLE:
                        slot["proc"].join(30)
                        slots[slots.index(slot)] = spawn(slot["n"])
                    if progress is not None:
                        progress(len(campaign.results), len(tasks))
                elif time.monotonic() - slot["since"] > 2 * time_limit_s + 10:
                    dead(slot, "hang", "worker stopped answering")
    finally:
        for slot in slots:
            with contextlib.suppress(OSError, BrokenPipeError):
                slot["conn"].send(None)
        for slot in slots:
            slot["proc"].join(5)
            if slot["proc"].is_alive():
                slot["proc"].kill()
    return campaign
