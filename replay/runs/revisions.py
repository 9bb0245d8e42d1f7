"""Another version of the code: a git worktree of a revision with its own virtual environment.

``prepare_revision`` checks the revision out with ``git worktree add --detach`` into
``<cache>/revs/<sha>/src`` and builds ``<cache>/revs/<sha>/venv`` (``python -m venv`` then
``pip install -e src``), once per commit sha; a ``ready`` stamp marks a finished build, a lock
file keeps two suites from building the same revision at once, and a failed build is removed
so that the next attempt starts clean. Cells run there through that environment's
``slamreplay run`` (which every revision has, unlike ``suite``), so results of a revision come
from its own code only: the checkout the user works in is never touched.

``SLAMREPLAY_REV_PYTHON`` names an interpreter that already has the dependencies, to use
instead of building a virtual environment (tests; a cluster image): cells then run the worktree's
own CLI with that interpreter (``_source_cli``), still the revision's code.

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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slamreplay.recorder.version import SOURCE_ROOT
from slamreplay.replay.engine.declared import DECLARATIONS_ENV, declaration_files
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs.suite_run import CellJob
from slamreplay.replay.tools.child import child_setup

BUILD_TIMEOUT_S = 1800


@dataclass(frozen=True, slots=True)
class Revision:
    """A built revision: its commit, worktree and the command that runs ``slamreplay``."""

    rev: str
    sha: str
    worktree: Path
    command: tuple[str, ...]
    env: dict[str, str]
    repo: Path | None = None  # the checkout the worktree was made from


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
    with open(path, "w") as f:
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
STEP_NOTES = {"git worktree add": "git worktree add (a checkout of it)",
              "python -m venv": "python -m venv (its own virtual environment)",
              "pip install -e": "pip install -e (it and its dependencies: about a minute)"}


def prepare_revision(repo: Path, rev: str, cache: Path, note: Callable[[str], None] | None = None) -> Revision:
    """Worktree and environment of ``rev``, built once per commit; ReplayError if it does not build.

    ``note(text)`` is told before the build and each of its slow steps, and when a finished build is
    reused; the command line prints it (a build is a minute or more of silence otherwise).
    """
    note = note or (lambda text: None)
    sha = resolve(repo, rev)
    root = cache / "revs" / sha
    src, venv = root / "src", root / "venv"
    program = not is_slamreplay_checkout(repo)
    if program:
        note(f"{rev} is a revision of {repository_of_revisions(repo)}")
    override = os.environ.get("SLAMREPLAY_REV_PYTHON") or (sys.executable if program else None)
    lock = cache / "revs" / f".{sha}.lock"
    shown = sha[:10] if rev == sha else f"{rev} ({sha[:10]})"
    if not (root / "ready").is_file():
        note(f"building the environment of {shown}, once per commit; log: {root / 'build.log'}")
    with _locked(lock):
        if (root / "ready").is_file():
            note(f"using the environment of {shown} built before ({root})")
        else:
            _remove_build(repo, root)
            root.mkdir(parents=True, exist_ok=True)
            log = root / "build.log"
            steps = [("git worktree add", ["git", "worktree", "add", "--detach", str(src), sha])]
            if not override:
                steps += [("python -m venv", [sys.executable, "-m", "venv", str(venv)]),
                          ("pip install -e", [str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet", "-e",
                                              str(src)])]
            with open(log, "w") as out:
                for name, step in steps:
                    note(STEP_NOTES[name])
                    out.write(f"$ {' '.join(step)}\n")
                    out.flush()
                    try:
                        done = subprocess.run(step, cwd=repo, stdout=out, stderr=subprocess.STDOUT,
                                              timeout=BUILD_TIMEOUT_S)
                    except (OSError, subprocess.SubprocessError) as err:
                        done = subprocess.CompletedProcess(step, 1, None, None)
                        out.write(f"{err}\n")
                    if done.returncode != 0:
                        keep = cache / "revs" / f"{sha}.failed-build.log"
                        shutil.copy(log, keep)
                        out.close()
                        _remove_build(repo, root)
                        raise ReplayError(f"revision {rev} ({sha[:10]}) does not build: `{name}` failed; "
                                          f"see {keep}")
            (root / "ready").write_text(sha + "\n")
    if program:  # this slamreplay, the program's worktree
        return Revision(rev, sha, src, (sys.executable, "-c", _INSTALLED_CLI), {}, repo)
    if override:
        return Revision(rev, sha, src, (override, "-c", _source_cli(src), str(src)), {}, repo)
    return Revision(rev, sha, src, (str(venv / "bin" / "slamreplay"),), {}, repo)


# ``python -c`` programs running a checkout's CLI without installing it: since the packages moved under the
# ``slamreplay`` namespace (a package-dir mapping only an install sets up) a namespace module whose path is the
# checkout stands in for the install; a revision from before the move imports its bare top-level packages.
_NAMESPACED_CLI = ("import sys, types; src = sys.argv.pop(1); ns = types.ModuleType('slamreplay'); "
                   "ns.__path__ = [src]; sys.modules['slamreplay'] = ns; "
                   "from slamreplay.api.cli import main; sys.exit(main(sys.argv[1:]))")
_INSTALLED_CLI = "import sys; from slamreplay.api.cli import main; sys.exit(main(sys.argv[1:]))"
_BARE_CLI = "import sys; sys.path.insert(0, sys.argv.pop(1)); from api.cli import main; sys.exit(main(sys.argv[1:]))"


def _source_cli(src: Path) -> str:
    """The ``python -c`` program that runs the CLI of the checkout ``src`` (see above)."""
    namespaced = '"slamreplay.api" = "api"' in (src / "pyproject.toml").read_text()
    return _NAMESPACED_CLI if namespaced else _BARE_CLI


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
