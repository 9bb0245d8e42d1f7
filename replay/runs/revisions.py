"""Another version of the code: a git worktree of a revision, run with an environment of its dependencies.

``prepare_revision`` checks the revision out with ``git worktree add --detach`` into ``<cache>/revs/<sha>/src``
and lays out ``<cache>/revs/<sha>/site`` beside it: the revision's own code as an install would present it
(a ``slamreplay`` namespace whose folders link into the worktree, and a dist-info with the revision's version and
entry points, so its pipelines and importers are found; ``slamreplay.replay.runs.rev_envs``). Its dependencies
come from an environment shared by every commit that declares the same ones: ``<cache>/envs/<key>/``, keyed by
the interpreter's version and the revision's ``[project] dependencies``, ``requires-python`` and lock file, holding
only dependencies and built once (``python -m venv`` and ``pip install``, about a minute; uv when it is there).
Cells run there through the revision's own CLI, ``<env>/bin/python`` with ``site/`` first on ``PYTHONPATH``, so
results of a revision come from its own code only: the checkout the user works in is never touched. A revision
costs a worktree (about 15 MB and a second); a new environment only comes with changed dependencies (about 1 GB).

A ``ready`` stamp marks a finished build of each, a lock file keeps two processes from building the same one at
once, and a failed build is removed so that the next attempt starts clean. A ``Revision`` holds its revision and
its environment in use while it lives; the cache is pruned to ``$SLAMREPLAY_CACHE_LIMIT_GB`` (default 10), least
recently used first and never what is in use, after each revision prepared (``slamreplay.replay.runs.rev_cache``;
``slamreplay cache`` lists and prunes it).

``SLAMREPLAY_REV_PYTHON`` names an interpreter that already has the dependencies, to use instead of an
environment (tests; a cluster image): cells run the worktree's own CLI with that interpreter, the same ``site/``
first on its path, so still the revision's code and metadata even if that interpreter has slamreplay installed.

A revision of **an external program's own repository** (docs/external.md: a declaration that lives in
a git checkout other than slamreplay's, e.g. ``compare rev:HEAD~1 rev:HEAD`` run inside it) is that
repository's worktree with no environment of its own: cells run with this slamreplay, the
declaration is read from the worktree (``revision_env``) and its ``build`` key builds the program
there, so only the program differs between two such revisions.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from slamreplay.recorder.files import atomic_write
from slamreplay.recorder.version import SOURCE_ROOT
from slamreplay.replay.engine.declared import DECLARATIONS_ENV, declaration_files
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.rev_cache import (
    Hold,
    build_lock,
    estimated_size,
    format_size,
    prune,
    record_size,
    total_size,
)
from slamreplay.replay.runs.rev_envs import (
    ENV_STEP_NOTES,
    DependencySpec,
    build_env,
    check_python,
    dependency_spec,
    env_python,
    interpreter_id,
    read_project,
    run_step,
    write_site,
)
from slamreplay.replay.runs.suite_run import CellJob
from slamreplay.replay.tools.cache import LIMIT_ENV, cache_limit
from slamreplay.replay.tools.child import child_setup


@dataclass(frozen=True, slots=True)
class Revision:
    """A built revision: its commit, worktree and the command that runs ``slamreplay``; while it lives, its
    ``hold`` keeps the revision and its environment in use (a copy sent elsewhere, e.g. to a Ray task, holds
    nothing)."""

    rev: str
    sha: str
    worktree: Path
    command: tuple[str, ...]
    env: dict[str, str]
    repo: Path | None = None  # the checkout the worktree was made from
    hold: Hold | None = field(default=None, compare=False, repr=False)

    def __reduce__(self) -> tuple[Any, ...]:
        return (Revision, (self.rev, self.sha, self.worktree, self.command, self.env, self.repo))


def revision_env(revision: Revision, env: dict[str, str]) -> dict[str, str]:
    """``env`` for a command at ``revision``: pipeline declarations (``$SLAMREPLAY_PIPELINES``) inside the checkout
    are read from the same path in the revision's worktree, so an external program declared in the repository
    (and built by its ``build`` key) is that revision's, as the Python code is."""
    files = env.get(DECLARATIONS_ENV)
    if not files or revision.repo is None:
        return env
    repo = revision.repo.resolve()
    mapped = []
    for entry in files.split(os.pathsep):
        p = Path(entry).resolve() if entry else None
        if p is not None and p.is_relative_to(repo):
            p = revision.worktree / p.relative_to(repo)
        mapped.append(str(p) if p is not None else entry)
    return {**env, DECLARATIONS_ENV: os.pathsep.join(mapped)}


def _git(repo: Path, *args: str) -> str:
    try:
        done = subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.SubprocessError) as err:
        raise ReplayError(f"git {' '.join(args)} failed: {err}") from None
    if done.returncode != 0:
        msg = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise ReplayError(f"git {' '.join(args)}: {msg}")
    return done.stdout


def find_repo(start: Path | None = None) -> Path:
    """The git checkout holding ``start`` (default: the current directory), else the running code's."""
    for where in (start or Path.cwd(), SOURCE_ROOT):
        try:
            return Path(_git(where, "rev-parse", "--show-toplevel").strip())
        except ReplayError:
            continue
    raise ReplayError("not in a git checkout: --rev and rev: need the slamreplay repository (cd into it)")


def is_slamreplay_checkout(repo: Path) -> bool:
    """Whether ``repo`` is a checkout of slamreplay itself (its pyproject.toml names the project)."""
    try:
        text = (repo / "pyproject.toml").read_text()
    except OSError:
        return False
    return any(line.replace(" ", "") == 'name="slamreplay"' for line in text.splitlines())


def declared_in(repo: Path) -> list[Path]:
    """The pipeline declaration files (``$SLAMREPLAY_PIPELINES``, ./pyproject.toml) that live inside ``repo``."""
    root = repo.resolve()
    return [p for p in declaration_files() if p.is_relative_to(root)]


def repository_of_revisions(repo: Path) -> str:
    """What ``rev:`` revisions of ``repo`` are, in words; ReplayError when they can be neither (see the module
    docstring): slamreplay's own code, or an external program declared inside ``repo``."""
    if is_slamreplay_checkout(repo):
        return f"slamreplay's repository {repo}"
    files = declared_in(repo)
    if not files:
        raise ReplayError(f"{repo} is neither slamreplay's repository nor holds a pipeline declaration of "
                          f"${DECLARATIONS_ENV}: a revision is slamreplay's code (cd into its checkout) or an "
                          f"external program's, declared in a file inside that program's repository (docs/external.md)")
    return (f"the program repository {repo} (declared in {', '.join(str(f.relative_to(repo.resolve())) for f in files)}"
            f"; run with this slamreplay)")


def resolve(repo: Path, rev: str) -> str:
    """The full commit sha of ``rev``; ReplayError for an unknown revision."""
    if not rev or rev.startswith("-"):
        raise ReplayError(f"unknown revision {rev!r}")
    try:
        return _git(repo, "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}").strip()
    except ReplayError:
        raise ReplayError(f"unknown revision {rev!r} in {repo}: give a commit, branch or tag that "
                          f"`git rev-parse` knows (fetch it first if it is remote)") from None


def commit_range(repo: Path, a: str, b: str, limit: int = 50) -> list[str]:
    """``git log --oneline A..B`` (at most ``limit`` lines)."""
    try:
        return _git(repo, "log", "--oneline", f"-{limit}", f"{a}..{b}").splitlines()
    except ReplayError:
        return []


def one_line(repo: Path, sha: str) -> str:
    """``git log --oneline -1 SHA``."""
    return _git(repo, "log", "--oneline", "-1", sha).strip()


def ancestry(repo: Path, good: str, bad: str) -> list[str]:
    """Commits after ``good`` up to ``bad`` on the path between them, oldest first; ReplayError if unrelated."""
    try:
        _git(repo, "merge-base", "--is-ancestor", good, bad)
    except ReplayError:
        raise ReplayError(f"{good} is not an ancestor of {bad}: bisect needs GOOD older than BAD "
                          f"on one line of history") from None
    return _git(repo, "rev-list", "--reverse", "--ancestry-path", f"{good}..{bad}").split()


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _remove_build(repo: Path, root: Path) -> None:
    if (root / "src").exists():
        subprocess.run(["git", "worktree", "remove", "--force", str(root / "src")], cwd=repo,
                       capture_output=True, timeout=120)
    shutil.rmtree(root, ignore_errors=True)
    subprocess.run(["git", "worktree", "prune"], cwd=repo, capture_output=True, timeout=120)


# What each build step is, for the note printed before it (a build is minutes of silence otherwise).
STEP_NOTES = {"git worktree add": "git worktree add (a checkout of it)", **ENV_STEP_NOTES}
REVISION_FORMAT = 2  # of revision.json: 1 had a virtual environment per commit (revs/<sha>/venv), no revision.json


def _ready(root: Path) -> dict[str, Any] | None:
    """``root``'s revision.json when it is a finished build of this format, else None."""
    if not (root / "ready").is_file():
        return None
    try:
        info = json.loads((root / "revision.json").read_text())
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) and info.get("format") == REVISION_FORMAT else None


def _spec_of(info: Mapping[str, Any]) -> DependencySpec:
    """The dependency spec a revision.json recorded, with this interpreter (an upgraded Python: a new key)."""
    d = info["dependencies"]
    return DependencySpec(interpreter_id(), tuple(d["dependencies"]), d["requires_python"],
                          tuple(sorted(d["locks"].items())))


def _ensure_env(spec: DependencySpec, cache: Path, src: Path, log: Path, hold: Hold,
                note: Callable[[str], None]) -> Path:
    """The environment of ``spec``, built once (under its lock; removed when it fails), held in use by ``hold``."""
    env = cache / "envs" / spec.key
    with _locked(build_lock(env)):
        if not (env / "ready").is_file():
            check_python(spec)
            note(f"building the environment of its dependencies ({spec.key}, {len(spec.dependencies)} of them), "
                 f"shared by every commit that declares the same; log: {log}")
            try:
                with open(log, "a") as out:

                    def step(name: str, argv: list[str]) -> None:
                        note(STEP_NOTES[name])
                        run_step(name, argv, src, out)

                    build_env(spec, env, src, step)
            except BaseException:
                shutil.rmtree(env, ignore_errors=True)
                raise
            shutil.copy(log, env / "build.log")
            record_size(env)
        hold.take(env)
    return env


def prepare_revision(repo: Path, rev: str, cache: Path, note: Callable[[str], None] | None = None) -> Revision:
    """Worktree of ``rev`` and the environment of its dependencies (see the module docstring); ReplayError if it
    does not build. The revision and its environment are in use (never pruned) while the Revision lives.

    ``note(text)`` is told before the build and each of its slow steps, and when a finished build is
    reused; the command line prints it (a build is a minute or more of silence otherwise).
    """
    note = note or (lambda text: None)
    sha = resolve(repo, rev)
    root = cache / "revs" / sha
    src = root / "src"
    program = not is_slamreplay_checkout(repo)
    if program:
        note(f"{rev} is a revision of {repository_of_revisions(repo)}")
    override = os.environ.get("SLAMREPLAY_REV_PYTHON") or None
    shown = sha[:10] if rev == sha else f"{rev} ({sha[:10]})"
    hold = Hold()
    if _ready(root) is None:
        note(f"building the environment of {shown}: its worktree, its dependencies' environment shared with "
             f"the commits that declare the same; log: {root / 'build.log'}")
    with _locked(build_lock(root)):
        info = _ready(root)
        if info is not None:
            note(f"using the environment of {shown} built before ({root})")
        env = None
        try:
            if info is None:
                _remove_build(repo, root)
                root.mkdir(parents=True, exist_ok=True)
                (root / "build.log").write_text("")
                info = _build(repo, sha, root, cache, program, note)
            if not program and not override:
                env = _ensure_env(_spec_of(info), cache, src, root / "build.log", hold, note)
        except ReplayError as err:
            hold.release()
            keep = cache / "revs" / f"{sha}.failed-build.log"
            if (root / "build.log").is_file():
                shutil.copy(root / "build.log", keep)
            if _ready(root) is None:
                _remove_build(repo, root)
            raise ReplayError(f"revision {rev} ({sha[:10]}) does not build: {err}; see {keep}") from None
        (root / "ready").write_text(sha + "\n")
        hold.take(root)
    if program:  # this slamreplay, the program's worktree
        revision = Revision(rev, sha, src, (sys.executable, "-c", _INSTALLED_CLI), {}, repo, hold)
    else:
        python = override or (str(env_python(env)) if env is not None else sys.executable)
        path = os.pathsep.join([*info["site"]["path"], *filter(None, [os.environ.get("PYTHONPATH")])])
        revision = Revision(rev, sha, src, (python, "-c", info["site"]["program"]), {"PYTHONPATH": path}, repo, hold)
    _prune_over_limit(cache, note)
    return revision


def _build(repo: Path, sha: str, root: Path, cache: Path, program: bool, note: Callable[[str], None]
           ) -> dict[str, Any]:
    """Check ``sha`` out into ``root/src`` and lay out its ``site/``; what revision.json records."""
    src = root / "src"
    with open(root / "build.log", "a") as out:
        note(STEP_NOTES["git worktree add"])
        run_step("git worktree add", ["git", "worktree", "add", "--detach", str(src), sha], repo, out)
    try:
        subject = one_line(repo, sha).partition(" ")[2]
    except ReplayError:
        subject = ""
    info: dict[str, Any] = {"format": REVISION_FORMAT, "sha": sha, "subject": subject, "repo": str(repo.resolve()),
                            "program": program}
    if not program:
        project = read_project(src)
        spec = dependency_spec(src, project)
        site = write_site(src, root / "site", project)
        info.update(env=spec.key, dependencies=spec.to_json(), site={"path": list(site.path),
                                                                       "program": site.program})
    atomic_write(root / "revision.json", json.dumps(info, indent=2) + "\n")
    record_size(root)
    return info


def _prune_over_limit(cache: Path, note: Callable[[str], None]) -> None:
    """Prune the cache to its limit when it holds more (``slamreplay.replay.runs.rev_cache``)."""
    limit = cache_limit()
    if estimated_size(cache) <= 0.9 * limit or total_size(cache) <= limit:  # the margin: __pycache__ since
        return
    done = prune(cache, limit, note)
    if done.after > limit:
        note(f"the revision cache holds {format_size(done.after)}, over its limit of {format_size(limit)} "
             f"(${LIMIT_ENV}): the rest is in use")


# ``python -c`` program running slamreplay's installed CLI (an external program's revision: this slamreplay).
_INSTALLED_CLI = "import sys; from slamreplay.api.cli import main; sys.exit(main(sys.argv[1:]))"


def run_cell(revision: Revision, job: CellJob) -> str | None:
    """Run one cell with the revision's ``slamreplay run``; an error message, or None on success."""
    return run_at(revision, job.recording.path, job.cell.pipeline, job.run_dir, job.cell.seed, job.cell.config,
                  job.recording.topic_map)


def run_at(revision: Revision, recording: Path, pipeline: str, run_dir: Path, seed: int, config: Mapping[str, Any],
           topic_map: Mapping[str, str]) -> str | None:
    """Replay ``recording`` through ``pipeline`` into ``run_dir`` (which must not exist) with the revision's
    ``slamreplay run``; an error message (the command's last line), or None on success."""
    run_dir = run_dir.resolve()  # the command runs in the worktree: a relative path would miss (so would the
    # recording's, made absolute without resolving a link: the service names its files by link)
    cfg = run_dir.parent / f".{run_dir.name}.config.json"
    cfg.write_text(json.dumps(dict(config), sort_keys=True))
    cmd = [*revision.command, "run", str(recording.absolute()), "--pipeline", pipeline,
           "--out", str(run_dir), "--seed", str(seed), "--config", str(cfg), "--quiet"]
    for k, v in sorted(topic_map.items()):
        cmd += ["--topic-map", f"{k}={v}"]
    env = revision_env(revision, {**os.environ, **revision.env})
    try:
        done = subprocess.run(cmd, cwd=revision.worktree, capture_output=True, text=True, env=env,
                              preexec_fn=child_setup())  # dies with the worker that started it (a cancel)
    except OSError as err:
        return f"cannot start {cmd[0]}: {err}"
    finally:
        cfg.unlink(missing_ok=True)
    if done.returncode != 0:
        lines = done.stderr.strip().splitlines()
        return lines[-1] if lines else f"slamreplay run exited with {done.returncode}"
    return None


def run_cells(revision: Revision, jobs: list[CellJob], workers: int) -> Iterable[tuple[CellJob, str | None]]:
    """Run ``jobs`` at the revision, ``workers`` at once; yields (job, error) as they end."""
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        futures = {pool.submit(run_cell, revision, job): job for job in jobs}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()
