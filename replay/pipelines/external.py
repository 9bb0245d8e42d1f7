"""External programs as pipelines: a command line declared in TOML instead of Python code (docs/external.md).

A declaration (``[pipelines.NAME]`` of a file ``slamreplay.replay.engine.declared`` finds) names a command
with placeholders for the recording, the exports slamreplay writes for it, and the folder the program
writes its estimate into. The replay reads the recording's ground truth (drawn as it goes); at the end the
exports are written to a temporary folder, the program is run once (twice with ``check_determinism``) under
a wall-time and a memory limit, its TUM trajectory is read, moved to the true start pose (``frame =
"start"``) and scored as any pipeline's trajectory is. Its stdout and stderr go to the run's log (and the
Rerun log view) and to the artifacts ``program_stdout.txt``/``program_stderr.txt``; the manifest records the
command, the program's version string and the sha256 of its executable (``pipeline_origin``) and what the
run did (``pipeline_run``).
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
import subprocess
import sys
import tempfile
import time
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
from slamreplay.replay.tools.child import child_setup
from slamreplay.replay.tools.estimates import F64, I64, EstimateReplay, anchor_at, read_tum_ns
from slamreplay.replay.tools.export import EXPORTS, export_recording, export_topics

PLACEHOLDERS = ("recording", "exports", "out", "seed", "config", "here", "python")
KEYS = {"command", "summary", "exports", "stdin", "output", "version_command", "timeout_s", "memory_mib", "frame",
        "topics", "config", "env", "adapter", "build", "landmarks"}
BUILD_TIMEOUT_S = 600.0
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
    if "check_determinism" in config:
        raise ReplayError(f"{where}: config key check_determinism is slamreplay's own: choose another name")
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


def program_version(decl: Declaration) -> str:
    """The first line the version command prints ('' without one; the error, shortened, when it fails)."""
    if not decl.version_command:
        return ""
    argv = [_expand(a, static_values(decl)) for a in decl.version_command]
    try:
        out = subprocess.run(argv, cwd=decl.here, capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.TimeoutExpired) as err:
        return f"unknown ({type(err).__name__})"
    lines = (out.stdout or out.stderr).strip().splitlines()
    return lines[0][:200] if lines else ""


def build_program(decl: Declaration) -> None:
    """Run the declaration's ``build`` command in its folder (once per process and declaration; a lock keeps two
    processes from building one folder at once). It should be idempotent and quick when nothing changed (make):
    at a git revision (``compare rev:``, ``history``) the declaration is read from that revision's worktree, so
    the program built is that revision's."""
    if not decl.build:
        return
    import fcntl

    argv = [_expand(a, static_values(decl)) for a in decl.build]
    lock = Path(tempfile.gettempdir()) / f"slamreplay-build-{hashlib.sha256(str(decl.here).encode()).hexdigest()[:16]}"
    with open(lock, "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        try:
            done = subprocess.run(argv, cwd=decl.here, capture_output=True, text=True, timeout=BUILD_TIMEOUT_S,
                                  check=False)
        except (OSError, subprocess.TimeoutExpired) as err:
            raise ReplayError(f"external pipeline {decl.name}: build {' '.join(argv)} in {decl.here} did not run: "
                              f"{err}") from None
    if done.returncode != 0:
        last = _last_line(done.stderr) or _last_line(done.stdout)
        raise ReplayError(f"external pipeline {decl.name}: build {' '.join(argv)} in {decl.here} exited with "
                          f"{done.returncode}: {last}")


def origin_of(decl: Declaration) -> dict[str, Any]:
    """``pipeline_origin`` of a run: the declaration, the command, the program's version and file hashes."""
    values = static_values(decl)
    argv = [_expand(a, values) for a in decl.command]
    exe = _resolve(argv[0], decl.here)
    files = {a: _sha256(decl.here / a) for a in argv[1:] if "{" not in a and (decl.here / a).is_file()}
    return {"distribution": "external", "version": program_version(decl), "entry_point": f"{decl.path}:{decl.name}",
            "command": list(decl.command), "executable": str(exe) if exe else argv[0],
            "executable_sha256": _sha256(exe) if exe else None, "files_sha256": files,
            "declaration_sha256": _sha256(decl.path)}


@dataclass(frozen=True, slots=True)
class ProgramRun:
    """What one run of the program did."""

    argv: list[str]
    status: int
    stdout: str
    stderr: str
    wall_s: float
    output: bytes | None
    landmarks: bytes | None = None  # the landmark map the program wrote (``Declaration.landmarks``), if any


def run_program(decl: Declaration, values: Mapping[str, str], out_dir: Path) -> ProgramRun:
    """Run the program once with ``values`` for the placeholders, its output folder ``out_dir`` (created)."""
    out_dir.mkdir(parents=True)
    argv = [_expand(a, values) for a in decl.command]
    exe = _resolve(argv[0], decl.here)
    if exe is None:
        raise ReplayError(f"external pipeline {decl.name}: program {argv[0]} not found (relative to {decl.here} "
                          f"or on PATH; a compiled example is built by `make examples`)")
    argv[0] = str(exe)
    env = {**os.environ, **{f"SLAMREPLAY_{k.upper()}": v for k, v in values.items() if k != "here"},
           **{k: _expand(v, values) for k, v in decl.env.items()}}
    stdin_path = Path(_expand(decl.stdin, values)) if decl.stdin else None
    tic = time.perf_counter()
    with open(stdin_path if stdin_path else os.devnull, "rb") as stdin:
        try:
            proc = subprocess.Popen(argv, cwd=decl.here, stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    env=env, start_new_session=True, preexec_fn=child_setup(decl.memory_mib))
        except OSError as err:
            raise ReplayError(f"external pipeline {decl.name}: cannot start {argv[0]}: {err.strerror}") from None
        try:
            out, err_bytes = proc.communicate(timeout=decl.timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            raise ReplayError(f"external pipeline {decl.name}: {Path(argv[0]).name} ran past its wall-time limit of "
                              f"{decl.timeout_s:g} s and was killed (timeout_s in {decl.path})") from None
    stdout, stderr = out.decode(errors="replace"), err_bytes.decode(errors="replace")
    output = Path(_expand(decl.output, values))
    marks = Path(_expand(decl.landmarks, values)) if decl.landmarks else None
    return ProgramRun(argv, proc.returncode, stdout, stderr, time.perf_counter() - tic,
                      output.read_bytes() if output.is_file() else None,
                      marks.read_bytes() if marks is not None and marks.is_file() else None)


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
    return lines[-1][:300] if lines else "nothing on stderr"


def check_outcome(decl: Declaration, run: ProgramRun) -> None:
    """ReplayError, one line naming the program and its last stderr line, unless it exited 0 with an output."""
    prog = Path(run.argv[0]).name
    if run.status < 0:
        sig = signal.Signals(-run.status).name
        mem = f" (memory limit {decl.memory_mib} MiB)" if decl.memory_mib else ""
        raise ReplayError(f"external pipeline {decl.name}: {prog} was killed by {sig}{mem}: {_last_line(run.stderr)}")
    if run.status != 0:
        mem = (f" (memory limit {decl.memory_mib} MiB: out of memory?)" if decl.memory_mib and
               "memory" in run.stderr.lower() else "")
        raise ReplayError(f"external pipeline {decl.name}: {prog} exited with status {run.status}{mem}: "
                          f"{_last_line(run.stderr)}")
    if run.output is None:
        raise ReplayError(f"external pipeline {decl.name}: {prog} exited 0 but wrote no {decl.output}: "
                          f"{_last_line(run.stderr)}")


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
        decl = self.declaration
        topic_map = {t.file_topic: t.logical_topic for t in self.ctx.info.topics
                     if t.logical_topic and t.logical_topic != t.file_topic}
        config = {k: v for k, v in dataclasses.asdict(self.config).items() if k != "check_determinism"}
        with tempfile.TemporaryDirectory(prefix="slamreplay-external-") as tmp:
            root = Path(tmp)
            export_recording(self.ctx.info.path, root / "exports", decl.exports, topic_map)
            (root / "config.json").write_text(json.dumps(config, sort_keys=True))
            times = 2 if self.config.check_determinism else 1
            for k in range(times):
                values = {"recording": str(self.ctx.info.path.resolve()), "exports": str(root / "exports"),
                          "out": str(root / f"out{k}"), "seed": str(self.ctx.seed), "config": str(root / "config.json"),
                          "here": str(decl.here), "python": sys.executable}
                run = run_program(decl, values, root / f"out{k}")
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
        world = anchor_at(t_ns, poses, self.ctx.T_world_start) if decl.frame == "start" else poses
        if decl.landmarks:
            if first.landmarks is None:
                raise ReplayError(f"external pipeline {decl.name}: {Path(first.argv[0]).name} exited 0 but wrote no "
                                  f"{decl.landmarks}: {_last_line(first.stderr)}")
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
        tag = f" (run {k + 1} of {times})" if times > 1 else ""
        if k == 0 or run.status != 0:
            for stream, text in (("stdout", run.stdout), ("stderr", run.stderr)):
                lines = text.splitlines()
                for line in lines[:LOG_LINES]:
                    self.ctx.log(f"{stream}{tag}: {line}")
                if len(lines) > LOG_LINES:
                    self.ctx.log(f"{stream}{tag}: ... {len(lines) - LOG_LINES} more lines in program_{stream}.txt")

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
        out: dict[str, Any] = {"runs": [{"argv": r.argv, "exit_status": r.status, "wall_s": round(r.wall_s, 6)}
                                        for r in self.runs]}
        if self.deterministic is not None:
            out["determinism"] = {"checked": True, "deterministic": self.deterministic,
                                  "max_difference_m": self.max_difference_m}
        return out

    def artifacts(self) -> dict[str, bytes]:
        if not self.runs:
            return {}
        return {"program_stdout.txt": self.runs[0].stdout.encode(), "program_stderr.txt": self.runs[0].stderr.encode()}


def _config_class(decl: Declaration) -> type:
    fields = [(k, type(v), dataclasses.field(default=v, metadata={"help": "passed to the program in {config}"}))
              for k, v in decl.config.items()]
    fields.append(("check_determinism", bool, dataclasses.field(default=False, metadata={
        "help": "run the program twice and compare its outputs (manifest pipeline_run.determinism)"})))
    return dataclasses.make_dataclass(f"{decl.name}_config", fields, frozen=True)


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
