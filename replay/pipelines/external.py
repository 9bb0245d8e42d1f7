"""External programs as pipelines: a command line declared in TOML instead of Python code (docs/external.md).

A declaration (``[pipelines.NAME]`` of a file ``slamreplay.replay.engine.declared`` finds) names a command
with placeholders for the recording, the exports slamreplay writes for it, and the folder the program
writes its estimate into. The replay reads the recording's ground truth (drawn as it goes); at the end the
exports are written to a temporary folder, the program is run once (twice with ``check_determinism``, and on
the first run of each program: ``slamreplay.replay.tools.determinism``),
contained (``slamreplay.replay.tools.containment``: every process it starts is killed at its exit, its limit or
a cancel; its output is capped; a wall-time limit and an address-space limit, 4096 MiB unless declared), its TUM
trajectory is read, moved to the true start pose (``frame = "start"``) and scored as any pipeline's trajectory
is. Its stdout and stderr go to the run's log (the first ``LOG_LINES`` lines; and the Rerun log view) and to the
artifacts ``program_stdout.txt``/``program_stderr.txt``, kept by a failed run too, with the landmark map it
wrote (``program_landmarks.csv``); the manifest records the command, the program's version string and the
sha256 of its executable (``pipeline_origin``) and what the run did (``pipeline_run``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shlex
import shutil
import signal
import string
import sys
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.observe import Points
from slamreplay.recorder.messages import TOPIC_GROUND_TRUTH_LANDMARKS, TOPIC_ODOM, LandmarkMap
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.metric_registry import specs
from slamreplay.replay.tools.containment import (
    OUTPUT_CAP_BYTES,
    head_lines,
    memory_limit_mib,
    printable,
    read_result,
    run_contained,
)
from slamreplay.replay.tools import determinism
from slamreplay.replay.tools.estimates import F64, I64, CoverageConfig, EstimateReplay, anchor_at, read_tum_ns
from slamreplay.replay.tools.export import EXPORTS, export_recording, export_topics

PLACEHOLDERS = ("recording", "exports", "out", "seed", "config", "here", "python")
KEYS = {"command", "summary", "exports", "stdin", "output", "version_command", "timeout_s", "memory_mib", "frame",
        "topics", "config", "env", "adapter", "build", "landmarks"}
BUILD_TIMEOUT_S = 600.0
OWN_KEYS = frozenset({"check_determinism", "min_coverage"})  # config keys slamreplay reads, never the program
VERSION_TIMEOUT_S = 10.0
LOG_LINES = 200  # lines of each stream copied into the run's log; the whole stream is an artifact


@dataclass(frozen=True, slots=True)
class Declaration:
    """One external pipeline, as its TOML table declares it (docs/external.md lists the keys)."""

    name: str
    path: Path
    command: tuple[str, ...]
    summary: str
    exports: tuple[str, ...] = ()
    stdin: str | None = None
    output: str = "{out}/trajectory.tum"
    version_command: tuple[str, ...] = ()
    timeout_s: float = 600.0
    memory_mib: int | None = None
    frame: str = "start"
    topics: tuple[str, ...] = (TOPIC_ODOM,)
    config: Mapping[str, Any] = field(default_factory=dict)
    env: Mapping[str, str] = field(default_factory=dict)
    build: tuple[str, ...] = ()  # run in ``here`` before the program is first used in a process (e.g. make)
    landmarks: str | None = None  # the program's landmark map, CSV ``id,x_m,y_m`` (``read_landmarks``); optional

    @property
    def here(self) -> Path:
        return self.path.parent


def _argv(value: Any, key: str, where: str) -> tuple[str, ...]:
    if isinstance(value, str):
        value = shlex.split(value)
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        raise ReplayError(f"{where}: {key} must be a command line (a string or a list of strings)")
    return tuple(value)


def _check_placeholders(text: str, key: str, where: str) -> None:
    for _, name, _, _ in string.Formatter().parse(text):
        if name is not None and name not in PLACEHOLDERS:
            raise ReplayError(f"{where}: {key} names placeholder {{{name}}}; placeholders: "
                              f"{', '.join('{' + p + '}' for p in PLACEHOLDERS)}")


def parse_declaration(name: str, table: Mapping[str, Any], path: Path) -> Declaration:
    """A :class:`Declaration` from its TOML table; ReplayError naming the file and the key that is wrong."""
    where = f"{path} [pipelines.{name}]"
    unknown = set(table) - KEYS
    if unknown:
        raise ReplayError(f"{where}: unknown keys {', '.join(sorted(unknown))}; keys: {', '.join(sorted(KEYS))}")
    if "command" not in table:
        raise ReplayError(f"{where}: no command (the program's command line)")
    command = _argv(table["command"], "command", where)
    version = _argv(table["version_command"], "version_command", where) if "version_command" in table else ()
    build = _argv(table["build"], "build", where) if "build" in table else ()
    for arg in build:
        _check_placeholders(arg, "build", where)
        if any(f"{{{n}}}" in arg for n in PLACEHOLDERS if n not in ("here", "python")):
            raise ReplayError(f"{where}: build may name only {{here}} and {{python}} (it runs before any recording)")
    exports = table.get("exports", [])
    if not isinstance(exports, list) or any(e not in EXPORTS for e in exports):
        raise ReplayError(f"{where}: exports must be a list of {', '.join(EXPORTS)}, got {exports!r}")
    for key, text in [*(("command", c) for c in command), ("stdin", table.get("stdin") or ""),
                      ("output", table.get("output", "{out}")), ("landmarks", table.get("landmarks") or "")]:
        _check_placeholders(str(text), key, where)
    timeout = table.get("timeout_s", 600.0)
    memory = table.get("memory_mib")
    if not isinstance(timeout, (int, float)) or not timeout > 0:
        raise ReplayError(f"{where}: timeout_s must be a number of seconds > 0, got {timeout!r}")
    if memory is not None and (not isinstance(memory, int) or memory < 16):
        raise ReplayError(f"{where}: memory_mib must be a whole number of MiB >= 16, got {memory!r}")
    frame = table.get("frame", "start")
    if frame not in ("start", "world"):
        raise ReplayError(f"{where}: frame must be 'start' (the program starts at its own origin) or 'world', "
                          f"got {frame!r}")
    topics = table.get("topics") or list(export_topics(exports)) or [TOPIC_ODOM]
    config = table.get("config", {})
    if not isinstance(config, dict) or not all(isinstance(v, (bool, int, float, str)) for v in config.values()):
        raise ReplayError(f"{where}: config must be a table of key = default (bool, int, float or string)")
    for own in OWN_KEYS & set(config):
        raise ReplayError(f"{where}: config key {own} is slamreplay's own: choose another name")
    env = table.get("env", {})
    if not isinstance(env, dict):
        raise ReplayError(f"{where}: env must be a table of NAME = value")
    return Declaration(name, path, command, str(table.get("summary") or f"external program {command[0]}"),
                       tuple(exports), table.get("stdin"), str(table.get("output", "{out}/trajectory.tum")),
                       version, float(timeout), memory, frame, tuple(topics), dict(config),
                       {str(k): str(v) for k, v in env.items()}, build,
                       str(table["landmarks"]) if table.get("landmarks") else None)


def _expand(text: str, values: Mapping[str, str]) -> str:
    return text.format(**values)


def _resolve(program: str, here: Path) -> Path | None:
    """A command's program: relative to the declaration's folder when it has a slash, else on PATH."""
    if "/" in program:
        p = Path(program) if Path(program).is_absolute() else here / program
        return p if p.is_file() else None
    found = shutil.which(program)
    return Path(found) if found else None


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def static_values(decl: Declaration) -> dict[str, str]:
    """Placeholder values known before a run (the others stand for themselves in the manifest)."""
    return {"here": str(decl.here), "python": sys.executable, "recording": "{recording}", "exports": "{exports}",
            "out": "{out}", "seed": "{seed}", "config": "{config}"}


def _run_tool(decl: Declaration, argv: list[str], timeout_s: float, memory_mib: int | None) -> tuple[int | None,
                                                                                               bytes, str, str]:
    """A declaration's version or build command, contained as the program is: (exit status or None, the start of
    its stdout, its last stderr line, why it did not start or end); the status is None when it did not."""
    with tempfile.TemporaryDirectory(prefix="slamreplay-tool-", ignore_cleanup_errors=True) as tmp:
        exe = _resolve(argv[0], decl.here)
        done = run_contained([str(exe) if exe else argv[0], *argv[1:]], cwd=decl.here, env=dict(os.environ),
                             stdin=None, memory_mib=memory_mib, timeout_s=timeout_s, work=Path(tmp))
        with open(done.stdout_path, "rb") as f:
            head = f.read(1 << 16)
    why = (done.start_error or (f"past its limit of {timeout_s:g} s" if done.timed_out else ""))
    return (None if why else done.status), head, done.last_stderr_line, why


def program_version(decl: Declaration) -> str:
    """The first line the version command prints ('' without one; the reason, shortened, when it fails)."""
    if not decl.version_command:
        return ""
    argv = [_expand(a, static_values(decl)) for a in decl.version_command]
    status, out, last_err, why = _run_tool(decl, argv, VERSION_TIMEOUT_S, memory_limit_mib(decl.memory_mib))
    if status is None:
        return f"unknown ({why[:100]})"
    lines = head_lines(out, 1)[0] if out.strip() else [last_err]
    return lines[0][:200] if lines else ""


def build_program(decl: Declaration) -> None:
    """Run the declaration's ``build`` command in its folder (once per process and declaration; a lock keeps two
    processes from building one folder at once). It should be idempotent and quick when nothing changed (make):
    at a git revision (``compare rev:``, ``history``) the declaration is read from that revision's worktree, so
    the program built is that revision's. It is contained as the program is, without a memory limit."""
    if not decl.build:
        return
    import fcntl

    argv = [_expand(a, static_values(decl)) for a in decl.build]
    lock = Path(tempfile.gettempdir()) / f"slamreplay-build-{hashlib.sha256(str(decl.here).encode()).hexdigest()[:16]}"
    with open(lock, "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        status, out, last_err, why = _run_tool(decl, argv, BUILD_TIMEOUT_S, None)
    if status is None:
        raise ReplayError(f"external pipeline {decl.name}: build {' '.join(argv)} in {decl.here} did not run: {why}")
    if status != 0:
        last = last_err or _last_line(out.decode("utf-8", "replace"))
        raise ReplayError(f"external pipeline {decl.name}: build {' '.join(argv)} in {decl.here} exited with "
                          f"{status}: {last}")


def origin_of(decl: Declaration) -> dict[str, Any]:
    """``pipeline_origin`` of a run: the declaration, the command, the program's version and file hashes."""
    values = static_values(decl)
    argv = [_expand(a, values) for a in decl.command]
    exe = _resolve(argv[0], decl.here)
    files = {a: _sha256(decl.here / a) for a in argv[1:] if "{" not in a and (decl.here / a).is_file()}
    return {"distribution": "external", "version": program_version(decl), "entry_point": f"{decl.path}:{decl.name}",
            "command": list(decl.command), "executable": str(exe) if exe else argv[0],
            "executable_sha256": _sha256(exe) if exe else None, "files_sha256": files,
            "declaration_sha256": _sha256(decl.path), "build": list(decl.build)}


@dataclass(frozen=True, slots=True)
class ProgramRun:
    """What one run of the program did.

    ``stdout`` and ``stderr`` are what was kept of each stream (the first ``OUTPUT_CAP_BYTES``, then a line
    saying how many bytes were dropped); ``last_stderr`` is the last line it wrote on stderr, past the cap too.
    ``output`` and ``landmarks`` are the files it wrote, read by ``read_result`` (None: not written, or refused
    for the reason in ``output_problem``/``landmarks_problem``). ``killed`` names the processes killed besides
    its main one: left running at its exit, or alive at its time limit.
    """

    argv: list[str]
    status: int  # negative: killed by that signal
    stdout: bytes
    stderr: bytes
    wall_s: float
    output: bytes | None
    landmarks: bytes | None = None
    last_stderr: str = ""
    timed_out: bool = False
    killed: tuple[tuple[int, str], ...] = ()
    dropped: Mapping[str, int] = field(default_factory=dict)
    memory_mib: int = 0
    output_problem: str | None = None
    landmarks_problem: str | None = None


class ProgramError(ReplayError):
    """A run of an external program failed; ``artifacts`` are the files its run directory keeps all the same (the
    program's capped output, the landmark map it wrote)."""

    def __init__(self, message: str, artifacts: Mapping[str, bytes]) -> None:
        super().__init__(message)
        self.artifacts = dict(artifacts)


def run_program(decl: Declaration, values: Mapping[str, str], out_dir: Path,
                scratch: Path | None = None) -> ProgramRun:
    """Run the program once, contained, with ``values`` for the placeholders, its output folder ``out_dir``
    (created; its capped stdout and stderr go to a folder beside it); ``scratch``, the temporary folder holding
    them, is removed if this process dies during the run (``run_contained``)."""
    out_dir.mkdir(parents=True)
    argv = [_expand(a, values) for a in decl.command]
    exe = _resolve(argv[0], decl.here)
    if exe is None:
        raise ReplayError(f"external pipeline {decl.name}: program {argv[0]} not found (relative to {decl.here} "
                          f"or on PATH; a compiled example is built by `make examples`)")
    argv[0] = str(exe)
    env = {**os.environ, **{f"SLAMREPLAY_{k.upper()}": v for k, v in values.items() if k != "here"},
           **{k: _expand(v, values) for k, v in decl.env.items()}}
    stdin = Path(_expand(decl.stdin, values)) if decl.stdin else None
    if stdin is not None and not stdin.is_file():
        raise ReplayError(f"external pipeline {decl.name}: stdin {decl.stdin} is not a file ({stdin}); an export "
                          f"must be listed in exports to be written")
    memory = memory_limit_mib(decl.memory_mib)
    done = run_contained(argv, cwd=decl.here, env=env, stdin=stdin, memory_mib=memory, timeout_s=decl.timeout_s,
                         work=out_dir.with_name(out_dir.name + "-streams"), scratch=scratch)
    if done.status is None:
        raise ReplayError(f"external pipeline {decl.name}: cannot run {argv[0]}: {done.start_error}")
    out = Path(values["out"])
    output, output_problem = (read_result(Path(_expand(decl.output, values)), _inside(decl.output, out))
                              if done.status == 0 and not done.timed_out else (None, None))
    landmarks, landmarks_problem = (read_result(Path(_expand(decl.landmarks, values)), _inside(decl.landmarks, out))
                                    if decl.landmarks else (None, None))
    return ProgramRun(argv, done.status, done.stdout_path.read_bytes(), done.stderr_path.read_bytes(), done.wall_s,
                      output, landmarks, done.last_stderr_line, done.timed_out, done.killed, dict(done.dropped),
                      memory, output_problem, landmarks_problem)


def _inside(declared: str, out: Path) -> Path | None:
    """``out`` when a declared path is in the program's ``{out}`` (it must not lead out of it), else None."""
    return out if declared.startswith("{out}") else None


def read_landmarks(data: bytes, what: str) -> tuple[I64, F64]:
    """A landmark map ``id,x_m,y_m`` per line (a header line and ``#`` comments allowed): ids (n,) and positions
    (n, 2), in the same frame as the trajectory; ReplayError naming the line that is wrong."""
    try:
        text = data.decode()
    except UnicodeDecodeError:
        raise ReplayError(f"{what} is not text (CSV id,x_m,y_m expected)") from None
    ids: list[int] = []
    xy: list[tuple[float, float]] = []
    for n, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#") or (n == 1 and not line[0].isdigit() and line[0] != "-"):
            continue
        parts = [p.strip() for p in line.split(",")]
        try:
            i, x, y = int(parts[0]), float(parts[1]), float(parts[2])
        except (ValueError, IndexError):
            raise ReplayError(f"{what}, line {n}: expected id,x_m,y_m (an integer and two numbers), got "
                              f"{line[:80]!r}") from None
        if len(parts) != 3 or i < 0 or not (np.isfinite(x) and np.isfinite(y)):
            raise ReplayError(f"{what}, line {n}: expected id >= 0 and two finite numbers, got {line[:80]!r}")
        ids.append(i)
        xy.append((x, y))
    if len(set(ids)) != len(ids):
        raise ReplayError(f"{what}: landmark ids must be unique")
    return np.asarray(ids, np.int64), np.asarray(xy, np.float64).reshape(-1, 2)


def _last_line(text: str) -> str:
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return printable(lines[-1])[:300] if lines else "nothing on stderr"


def _last_stderr(run: ProgramRun) -> str:
    return printable(run.last_stderr)[:300] if run.last_stderr else "nothing on stderr"


def check_outcome(decl: Declaration, run: ProgramRun) -> None:
    """ReplayError, one line naming the program and its last stderr line, unless it exited 0 with an output."""
    prog = Path(run.argv[0]).name
    limit = f"memory limit {run.memory_mib} MiB"
    if run.timed_out:
        raise ReplayError(f"external pipeline {decl.name}: {prog} ran past its wall-time limit of {decl.timeout_s:g} s "
                          f"and was killed (timeout_s in {decl.path}): {_last_stderr(run)}")
    if run.status < 0:
        sig = signal.Signals(-run.status).name
        raise ReplayError(f"external pipeline {decl.name}: {prog} was killed by {sig} ({limit}): {_last_stderr(run)}")
    if run.status != 0:
        mem = f" ({limit}: out of memory?)" if "memory" in run.last_stderr.lower() else ""
        raise ReplayError(f"external pipeline {decl.name}: {prog} exited with status {run.status}{mem}: "
                          f"{_last_stderr(run)}")
    if run.output is None:
        if run.output_problem:
            raise ReplayError(f"external pipeline {decl.name}: {prog} exited 0 but its output {decl.output} "
                              f"{run.output_problem}")
        raise ReplayError(f"external pipeline {decl.name}: {prog} exited 0 but wrote no {decl.output}: "
                          f"{_last_stderr(run)}")


class ExternalPipeline(EstimateReplay):
    """Base of the classes :func:`pipeline_from_declaration` makes: one external program as a pipeline."""

    declaration: ClassVar[Declaration]
    declared_origin: ClassVar[dict[str, Any]]

    def __init__(self, config: Any, ctx: Any) -> None:
        super().__init__(config, ctx)
        self.true_landmarks: LandmarkMap | None = None
        self.landmark_map: tuple[I64, F64] | None = None  # the program's, in the world frame
        self.runs: list[ProgramRun] = []
        self.deterministic: bool | None = None
        self.max_difference_m: float | None = None

    def estimate(self, t_gt: I64, gt: F64) -> tuple[I64, F64]:
        try:
            return self._estimate()
        except ReplayError as err:  # the failed run keeps what the program wrote (run_recording writes it)
            if not self.runs or isinstance(err, ProgramError):
                raise
            raise ProgramError(str(err), self._kept_files(self.runs[-1])) from None

    def _estimate(self) -> tuple[I64, F64]:
        decl = self.declaration
        topic_map = {t.file_topic: t.logical_topic for t in self.ctx.info.topics
                     if t.logical_topic and t.logical_topic != t.file_topic}
        config = {k: v for k, v in dataclasses.asdict(self.config).items() if k not in OWN_KEYS}
        # a program may leave files it made unremovable: they must not turn its run into an internal error
        with tempfile.TemporaryDirectory(prefix="slamreplay-external-", ignore_cleanup_errors=True) as tmp:
            root = Path(tmp)
            export_recording(self.ctx.info.path, root / "exports", decl.exports, topic_map)
            (root / "config.json").write_text(json.dumps(config, sort_keys=True))
            remembered = None if self.config.check_determinism else determinism.known(self.declared_origin)
            times = 1 if remembered is not None else 2
            if remembered is not None:
                self.deterministic, self.max_difference_m = remembered["deterministic"], remembered["max_difference_m"]
            elif not self.config.check_determinism:
                self.ctx.log("determinism check: the first run of this program (its hashes): run twice on the same "
                             "input, the verdict kept for its later runs")
            for k in range(times):
                values = {"recording": str(self.ctx.info.path.resolve()), "exports": str(root / "exports"),
                          "out": str(root / f"out{k}"), "seed": str(self.ctx.seed), "config": str(root / "config.json"),
                          "here": str(decl.here), "python": sys.executable}
                run = run_program(decl, values, root / f"out{k}", scratch=root)
                self.runs.append(run)
                self._log_streams(run, k, times)
                check_outcome(decl, run)
        first = self.runs[0]
        assert first.output is not None
        try:
            text = first.output.decode()
        except UnicodeDecodeError:
            raise ReplayError(f"external pipeline {decl.name}: {decl.output} is not text (TUM expected)") from None
        try:
            t_ns, poses = read_tum_ns(text, f"{Path(first.argv[0]).name}'s output {Path(decl.output).name}")
        except ReplayError as err:
            raise ReplayError(f"external pipeline {decl.name}: {err}") from None
        if len(self.runs) == 2:
            self._compare_runs(t_ns, poses)
            determinism.remember(self.declared_origin, bool(self.deterministic), self.max_difference_m)
        world = anchor_at(t_ns, poses, self.ctx.T_world_start) if decl.frame == "start" else poses
        if decl.landmarks:
            if first.landmarks is None:
                raise ReplayError(f"external pipeline {decl.name}: {Path(first.argv[0]).name} exited 0 but " + (
                    f"its map {decl.landmarks} {first.landmarks_problem}" if first.landmarks_problem else
                    f"wrote no {decl.landmarks}: {_last_stderr(first)}"))
            ids, xy = read_landmarks(first.landmarks, f"external pipeline {decl.name}: {Path(decl.landmarks).name}")
            if len(poses) and decl.frame == "start":  # the map moves with the trajectory to the true start
                to_world = se2.compose(world[0], se2.inverse(poses[0]))
                xy = se2.transform_points(to_world, xy) if len(xy) else xy
            self.landmark_map = (ids, xy)
        self.ctx.log(f"{Path(first.argv[0]).name}: {len(t_ns):,} poses in {first.wall_s:.2f} s" +
                     (" (moved to the true start pose)" if decl.frame == "start" and
                      self.ctx.T_world_start is not None else ""))
        return t_ns, world

    def step(self, env: Any) -> None:
        if isinstance(env.msg, LandmarkMap):
            self.true_landmarks = env.msg
        super().step(env)

    def finish(self) -> dict[str, float]:
        """The trajectory's metrics, and with a declared landmark map its own: matched to the truth by id."""
        metrics = super().finish()
        if self.landmark_map is None:
            return metrics
        ids, xy = self.landmark_map
        self.ctx.observer.log("world/landmarks/estimate", Points(xy, radius=0.15))
        metrics["landmarks_mapped"] = float(len(ids))
        truth = self.true_landmarks
        if truth is None:
            return metrics
        self.ctx.observer.log("world/landmarks/truth", Points(np.asarray(truth.positions_m), radius=0.1))
        where = {int(i): k for k, i in enumerate(truth.landmark_ids.tolist())}
        matched = [k for k, i in enumerate(ids.tolist()) if i in where]
        metrics["landmarks_true"] = float(len(where))
        metrics["false_landmarks"] = float(len(ids) - len(matched))
        if matched:
            ref = np.asarray(truth.positions_m)[[where[int(ids[k])] for k in matched]]
            metrics["landmark_rmse_m"] = float(np.sqrt(np.mean(np.sum((xy[matched] - ref) ** 2, axis=1))))
        return metrics

    def _log_streams(self, run: ProgramRun, k: int, times: int) -> None:
        """The first ``LOG_LINES`` lines of each stream, what the cap dropped, and the processes killed."""
        tag = f" (run {k + 1} of {times})" if times > 1 else ""
        if k == 0 or run.status != 0:
            for stream, data in (("stdout", run.stdout), ("stderr", run.stderr)):
                lines, count = head_lines(data, LOG_LINES)
                for line in lines:
                    self.ctx.log(f"{stream}{tag}: {line}")
                if count > LOG_LINES:
                    self.ctx.log(f"{stream}{tag}: ... {count - LOG_LINES} more lines in program_{stream}.txt")
                if run.dropped.get(stream):
                    self.ctx.log(f"{stream}{tag}: {run.dropped[stream]:,} bytes past the first "
                                 f"{OUTPUT_CAP_BYTES >> 20} MiB were not kept")
        for pid, name in run.killed[:LOG_LINES]:
            self.ctx.log(f"{'alive at the wall-time limit' if run.timed_out else 'left'} `{printable(name)}` "
                         f"(pid {pid}) running{tag}: killed")
        if len(run.killed) > LOG_LINES:
            self.ctx.log(f"... and {len(run.killed) - LOG_LINES} more processes{tag}: killed")

    def _compare_runs(self, t_ns: I64, poses: F64) -> None:
        a, b = self.runs
        self.deterministic = a.output == b.output
        if self.deterministic:
            self.max_difference_m = 0.0
            self.ctx.log("determinism check: the two runs wrote identical output")
            return
        try:
            t2, p2 = read_tum_ns((b.output or b"").decode(errors="replace"), "second run's output")
            same_t = len(t2) == len(t_ns) and bool(np.all(t2 == t_ns))
            self.max_difference_m = float(np.max(np.hypot(*(p2[:, :2] - poses[:, :2]).T))) if same_t else None
        except ReplayError:
            self.max_difference_m = None
        self.ctx.log(f"determinism check: the two runs wrote different output (largest position difference "
                     f"{self.max_difference_m if self.max_difference_m is not None else 'n/a (other times)'} m): "
                     f"NOT deterministic")

    def provenance(self) -> dict[str, Any]:
        out: dict[str, Any] = {"runs": [{"argv": r.argv, "exit_status": r.status, "wall_s": round(r.wall_s, 6),
                                         "memory_limit_mib": r.memory_mib, "killed": [n for _, n in r.killed]}
                                        for r in self.runs]}
        if self.deterministic is not None:  # checked: by this run (True), or a run of the same program before
            out["determinism"] = {"checked": True if len(self.runs) == 2 else "cached",
                                  "deterministic": self.deterministic, "max_difference_m": self.max_difference_m}
        return out

    def artifacts(self) -> dict[str, bytes]:
        return self._kept_files(self.runs[0]) if self.runs else {}

    @staticmethod
    def _kept_files(run: ProgramRun) -> dict[str, bytes]:
        """The program's capped output and the landmark map it wrote, for the run directory."""
        files = {"program_stdout.txt": run.stdout, "program_stderr.txt": run.stderr}
        if run.landmarks is not None:
            files["program_landmarks.csv"] = run.landmarks
        return files


def _config_class(decl: Declaration) -> type:
    fields = [(k, type(v), dataclasses.field(default=v, metadata={"help": "passed to the program in {config}"}))
              for k, v in decl.config.items()]
    fields.append(("check_determinism", bool, dataclasses.field(default=False, metadata={
        "help": "run the program twice and compare its outputs (manifest pipeline_run.determinism), even when a "
                "run of the same program (same hashes) checked it before; the first run always checks"})))
    return dataclasses.make_dataclass(f"{decl.name}_config", fields, bases=(CoverageConfig,), frozen=True)


def pipeline_from_declaration(name: str, table: Mapping[str, Any], path: Path) -> type[ExternalPipeline]:
    """The pipeline class of one declaration (the default adapter of ``slamreplay.replay.engine.declared``)."""
    decl = parse_declaration(name, table, path)
    build_program(decl)
    landmark_specs = specs("landmarks_mapped", "landmarks_true", "false_landmarks", "landmark_rmse_m")
    attrs = {"name": name, "summary": decl.summary, "required_topics": decl.topics, "start_topic": decl.topics[0],
             "metrics": {**ExternalPipeline.metrics, **(landmark_specs if decl.landmarks else {})},
             "optional_topics": (*ExternalPipeline.optional_topics,
                                 *((TOPIC_GROUND_TRUTH_LANDMARKS,) if decl.landmarks else ())),
             "Config": _config_class(decl), "presets": {}, "declaration": decl, "declared_origin": origin_of(decl)}
    return type(f"External[{name}]", (ExternalPipeline,), attrs)
