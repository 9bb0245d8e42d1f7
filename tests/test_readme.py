"""The README and docs/ run as written: every sh/bash/console/python block, in order, in a fresh copy of the repository.

Each file gets its own copy (the tracked and unignored files of this checkout, as a new git
repository) with the environment's ``bin`` first on PATH, the way a reader who activated it
types the commands. A comment just before a block changes what happens to it:

- ``<!-- docs-test: skip (why) -->``: not run (opens a window, serves until Ctrl-C, takes minutes);
  reported as skipped with the reason.
- ``<!-- docs-test: needs PATH -->``: run when PATH (relative to the repository, e.g. a public
  dataset in ``../shared/data``) exists, else skipped saying it is missing.
- ``<!-- docs-test: given NAME (what) -->``: the test provides NAME first (``my_robot_bag``: a small
  ROS 2 bag), standing in for the reader's own file.

Shell blocks run with ``bash -eo pipefail``: a command that fails stops the block, so a block
shows an expected non-zero exit as ``cmd || echo ...``. At the end the copy must hold no new
untracked files: everything the blocks write goes to git-ignored folders (``runs/``, ``recordings/``).
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
SHELLS = {"sh", "bash", "console", "shell"}
RUN = SHELLS | {"python"}
BLOCK_TIMEOUT_S = 300
MARKER = re.compile(r"^<!--\s*docs-test:\s*(?P<kind>\S+)\s*(?P<arg>.*?)\s*-->\s*$")
FENCE = re.compile(r"^```(?P<lang>[\w-]*)\s*$")
PROVIDED = ("my_robot_bag", "robot_bag_db3")  # what `given` may name; written by _provide


@dataclass(frozen=True)
class Block:
    """A fenced block of a markdown file, with the docs-test marker just before it (if any)."""

    path: Path
    line: int
    lang: str
    code: str
    kind: str | None = None
    arg: str = ""

    @property
    def label(self) -> str:
        return f"{self.path.relative_to(REPO)}:{self.line}"


def parse(path: Path) -> list[Block]:
    """Fenced blocks of ``path``; a marker applies to the block that follows it after blank lines only."""
    lines = path.read_text().splitlines()
    out, i, pending = [], 0, None
    while i < len(lines):
        m = MARKER.match(lines[i].strip())
        f = FENCE.match(lines[i])
        if m:
            pending = (m["kind"], m["arg"], i + 1)
        elif f:
            end = next((j for j in range(i + 1, len(lines)) if lines[j].startswith("```")), None)
            if end is None:
                raise AssertionError(f"{path.name}:{i + 1}: a code block is never closed")
            kind, arg = (pending[0], pending[1]) if pending else (None, "")
            out.append(Block(path, i + 1, f["lang"], "\n".join(lines[i + 1:end]) + "\n", kind, arg))
            pending, i = None, end
        elif lines[i].strip() and pending:
            raise AssertionError(f"{path.name}:{pending[2]}: a docs-test marker must come just before a code block")
        i += 1
    return out


BLOCKS = [b for doc in DOCS for b in parse(doc)]


def test_markers_are_understood() -> None:
    """(In make test.) Every block names its language, each marker is known and explained, a given is provided."""
    for b in BLOCKS:
        assert b.lang, f"{b.label}: name the block's language (```sh, ```python ...)"
        if b.kind is None:
            continue
        assert b.kind in {"skip", "needs", "given"}, f"{b.label}: unknown docs-test marker {b.kind!r}"
        assert b.lang in RUN, f"{b.label}: a marker on a block that is never run"
        if b.kind == "skip":
            assert re.fullmatch(r"\(.{8,}\)", b.arg), f"{b.label}: say why in parentheses: skip (opens a window)"
        if b.kind == "given":
            assert b.arg.split()[0] in PROVIDED, f"{b.label}: the test cannot provide {b.arg.split()[0]!r}"
    assert sum(b.lang in RUN and b.kind != "skip" for b in BLOCKS) >= 10


def _copy_repo(dst: Path) -> Path:
    """The checkout's tracked and unignored files (what a fresh clone has, plus uncommitted work) as a new repo."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, check=True).stdout.decode().split("\0")
    repo = dst / "repo"
    for name in filter(None, listed):
        src = REPO / name
        if src.is_file():
            (repo / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, repo / name)
    (repo / ".venv").symlink_to(Path(sys.prefix))  # the environment `make venv` built, as if built here
    data = Path(os.environ.get("SLAMREPLAY_DATA", REPO.parent / "shared" / "data"))
    if data.is_dir():
        (dst / "shared").mkdir()
        (dst / "shared" / "data").symlink_to(data)  # ../shared/data from the copy, as beside the checkout
    git = ["git", "-c", "user.name=docs-test", "-c", "user.email=docs-test@localhost", "-c", "commit.gpgsign=false"]
    subprocess.run([*git, "init", "-q"], cwd=repo, check=True)
    (repo / ".git" / "info" / "exclude").write_text(".venv\n" + "\n".join(PROVIDED) + "\n")
    subprocess.run([*git, "add", "-A"], cwd=repo, check=True)
    subprocess.run([*git, "commit", "-q", "-m", "copy"], cwd=repo, check=True)
    return repo


@pytest.fixture(scope="module")
def workspaces(tmp_path_factory: pytest.TempPathFactory) -> dict[Path, Path]:
    """One fresh copy of the repository per markdown file, made when its first block runs."""
    return {}


def _workspace(workspaces: dict[Path, Path], doc: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    if doc not in workspaces:
        workspaces[doc] = _copy_repo(tmp_path_factory.mktemp(doc.stem))
    return workspaces[doc]


def _env(repo: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = sys.prefix
    env["SLAMREPLAY_DATA"] = str(repo.parent / "shared" / "data")
    return env


def _provide(name: str, repo: Path) -> None:
    """Write what a ``given`` marker names (the reader's own files) into the copy."""
    if (repo / name).exists():
        return
    if name == "robot_bag_db3":  # a sqlite3 bag with odometry, tf, IMU, scans, images (tests/recorder)
        spec = importlib.util.spec_from_file_location("ros2bag_fixtures",
                                                      REPO / "tests" / "recorder" / "ros2bag_fixtures.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules["ros2bag_fixtures"] = module  # its dataclass resolves annotations through sys.modules
        spec.loader.exec_module(module)
        module.write_bag(repo / name, "sqlite3", seconds=20.0)
        return
    spec = importlib.util.spec_from_file_location("ros2_fixtures", REPO / "tests" / "replay" / "ros2_fixtures.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.write_ros2_bag(repo / name)


def _script(b: Block) -> list[str]:
    if b.lang == "python":
        return [sys.executable, "-c", b.code]
    code = b.code
    if b.lang == "console":  # `$ cmd` lines are commands, the rest is output
        code = "\n".join(line[2:] for line in code.splitlines() if line.startswith("$ ")) + "\n"
    return ["bash", "-eo", "pipefail", "-c", code]


@pytest.mark.docs
@pytest.mark.parametrize("block", [b for b in BLOCKS if b.lang in RUN], ids=lambda b: b.label)
def test_block_runs_as_written(block: Block, workspaces: dict[Path, Path],
                               tmp_path_factory: pytest.TempPathFactory) -> None:
    """The block exits 0 in the copy, after the blocks before it in the same file."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        pytest.skip("the blocks run in order, in one process: make test-docs (pytest -m docs, without -n)")
    if block.kind == "skip":
        pytest.skip(f"{block.label} marked: skip {block.arg}")
    repo = _workspace(workspaces, block.path, tmp_path_factory)
    if block.kind == "needs" and not (repo / block.arg).exists():
        pytest.skip(f"{block.label} needs {block.arg}, which is not here (SLAMREPLAY_DATA: the public datasets)")
    if block.kind == "given":
        _provide(block.arg.split()[0], repo)
    try:
        proc = subprocess.run(_script(block), cwd=repo, env=_env(repo), capture_output=True, text=True,
                              timeout=BLOCK_TIMEOUT_S, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"{block.label} ran over {BLOCK_TIMEOUT_S} s:\n{block.code}\n{err.stdout}\n{err.stderr}")
    assert proc.returncode == 0, (f"{block.label} exited {proc.returncode}:\n{block.code}\n--- stdout\n"
                                  f"{proc.stdout[-3000:]}\n--- stderr\n{proc.stderr[-3000:]}")


@pytest.mark.docs
@pytest.mark.parametrize("doc", sorted({b.path for b in BLOCKS if b.lang in RUN and b.kind != "skip"}),
                         ids=lambda d: str(d.relative_to(REPO)))
def test_blocks_leave_the_repository_clean(doc: Path, workspaces: dict[Path, Path]) -> None:
    """After its blocks ran, the copy has no new untracked or modified files: outputs go to ignored folders."""
    if doc not in workspaces:
        pytest.skip(f"no block of {doc.name} ran")
    status = subprocess.run(["git", "status", "--porcelain"], cwd=workspaces[doc], capture_output=True,
                            text=True, check=True).stdout
    assert status == "", f"{doc.name}'s blocks left files in the repository:\n{status}"


@pytest.fixture(scope="module")
def fresh_demo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh `slamreplay demo`, run once for the figures and the pictures alike (about 2 minutes)."""
    demo = tmp_path_factory.mktemp("fresh") / "demo"
    exe = Path(sys.executable).parent / "slamreplay"
    proc = subprocess.run([str(exe), "demo", "--out", str(demo), "--quiet"], capture_output=True, text=True,
                          timeout=900, stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return demo


@pytest.mark.docs
def test_figures_quoted_from_the_demo_match_a_fresh_demo(fresh_demo: Path) -> None:
    """Every ``<!-- demo: ... -->`` figure of README.md and docs/ equals what a fresh `slamreplay demo` gives
    (docs/demo_figures.py; `make readme-figures` rewrites them on purpose)."""
    check = subprocess.run([sys.executable, str(REPO / "docs" / "demo_figures.py"), "--demo", str(fresh_demo),
                            "--check"], capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    assert " 0 differ" in check.stdout and "0 figure(s)" not in check.stdout


@pytest.mark.docs
def test_pictures_show_what_a_fresh_demo_gives(fresh_demo: Path) -> None:
    """Every value a demo picture's record says it shows (docs/images/pictures.json) equals a fresh demo's within
    the metric's tolerance, as `diff` judges it (`make snapshots` remakes the pictures on purpose)."""
    from slamreplay.replay.runs.diff import metric_tolerance

    spec = importlib.util.spec_from_file_location("pictures", REPO / "docs" / "pictures.py")
    assert spec is not None and spec.loader is not None
    pictures = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(pictures)
    records = pictures.load()
    assert any(r.get("source") == "demo" and r.get("metrics") for r in records.values())
    found = pictures.value_problems(records, fresh_demo, metric_tolerance)
    assert not found, "\n".join(found) + "\n(make snapshots remakes the pictures and their records)"
