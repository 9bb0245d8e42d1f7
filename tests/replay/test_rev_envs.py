"""Revisions' environments shared by their dependencies; each revision's own code, metadata and entry points."""

from __future__ import annotations

import json
import os
import subprocess
import zipfile
from pathlib import Path

import pytest

from slamreplay.replay.errors import ReplayError
from slamreplay.replay.runs import rev_cache
from slamreplay.replay.runs.revisions import Revision, prepare_revision

CLI = '''import json, sys
from importlib import metadata
from pathlib import Path


def main(argv=None):
    eps = sorted(ep.name for ep in metadata.entry_points(group="slamreplay.pipelines"))
    try:
        import tinydep
        dep = tinydep.VALUE
    except ImportError:
        dep = None
    print(json.dumps({"marker": Path(__file__).with_name("marker.txt").read_text().strip(), "file": __file__,
                      "version": metadata.version("slamreplay"), "pipelines": eps, "dep": dep,
                      "argv": list(sys.argv[1:] if argv is None else argv)}))
    return 0
'''


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(repo), *args],
                          check=True, capture_output=True, text=True).stdout.strip()


def pyproject(version: str, deps: list[str], namespaced: bool = True) -> str:
    module = "slamreplay.api.cli" if namespaced else "api.cli"
    text = (f'[project]\nname = "slamreplay"\nversion = "{version}"\nrequires-python = ">=3.10"\n'
            f"dependencies = {json.dumps(deps)}\n"
            f'[project.scripts]\nslamreplay = "{module}:main"\n'
            f'[project.entry-points."slamreplay.pipelines"]\np{version.replace(".", "")} = "{module}:main"\n')
    return text + ('[tool.setuptools.package-dir]\n"slamreplay.api" = "api"\n' if namespaced else "")


def tiny_wheel(root: Path) -> Path:
    """A pure-Python wheel, tinydep 1.0 (VALUE = 7): a dependency pip installs with no index."""
    path = root / "tinydep-1.0-py3-none-any.whl"
    files = {"tinydep/__init__.py": "VALUE = 7\n",
             "tinydep-1.0.dist-info/METADATA": "Metadata-Version: 2.1\nName: tinydep\nVersion: 1.0\n",
             "tinydep-1.0.dist-info/WHEEL": "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\n"
                                            "Tag: py3-none-any\n"}
    files["tinydep-1.0.dist-info/RECORD"] = "".join(f"{f},,\n" for f in [*files, "tinydep-1.0.dist-info/RECORD"])
    with zipfile.ZipFile(path, "w") as z:
        for name, text in files.items():
            z.writestr(name, text)
    return path


@pytest.fixture
def project(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, list[str]]:
    """The repository of ``make_project``, and its shas."""
    return make_project(tmp_path, monkeypatch)


def make_project(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, list[str]]:
    """A slamreplay-named repository of 4 commits: top-level packages (as before the namespace), then the
    namespace (same dependencies), a code change (same dependencies), then a new dependency; their shas."""
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("SLAMREPLAY_REV_PYTHON", raising=False)
    monkeypatch.setenv("PIP_NO_INDEX", "1")  # nothing from the network: the one dependency is a local wheel
    monkeypatch.setenv("SLAMREPLAY_REV_INSTALLER", "pip")
    repo = tmp_path / "repo"
    (repo / "api").mkdir(parents=True)
    git(repo, "init", "-q")
    (repo / "api" / "__init__.py").write_text("")
    (repo / "api" / "cli.py").write_text(CLI)
    wheel = tiny_wheel(tmp_path)
    shas = []
    for i, (version, deps, namespaced) in enumerate([("0.1", [], False), ("0.2", [], True), ("0.3", [], True),
                                                     ("0.4", [f"tinydep @ {wheel.as_uri()}"], True)]):
        (repo / "pyproject.toml").write_text(pyproject(version, deps, namespaced))
        (repo / "api" / "marker.txt").write_text(f"commit {i}\n")
        git(repo, "add", "-A")
        git(repo, "commit", "-qm", f"commit {i}")
        shas.append(git(repo, "rev-parse", "HEAD"))
    return repo, shas


def cli(revision: Revision, *args: str) -> dict[str, object]:
    """What the revision's CLI (as cells run it) says about itself."""
    done = subprocess.run([*revision.command, *args], cwd=revision.worktree, capture_output=True, text=True,
                          env={**os.environ, **revision.env}, check=True)
    return json.loads(done.stdout)  # type: ignore[no-any-return]


def test_same_dependencies_share_one_environment(project: tuple[Path, list[str]], tmp_path: Path) -> None:
    """Three commits with the same dependencies: one environment, three worktrees; each runs its own code,
    version and entry points, the oldest one from its top-level packages."""
    repo, shas = project
    cache = tmp_path / "cache"
    revisions = [prepare_revision(repo, sha, cache) for sha in shas[:3]]
    assert len(list((cache / "envs").iterdir())) == 3  # one environment and its two lock files
    assert [p.name for p in (cache / "envs").iterdir() if p.is_dir()] == [revisions[0].command[0].split("/")[-3]]
    assert sorted(p.name for p in (cache / "revs").iterdir() if p.is_dir()) == sorted(shas[:3])
    for i, (sha, revision) in enumerate(zip(shas[:3], revisions, strict=True)):
        said = cli(revision, "run", "x")
        assert said["marker"] == f"commit {i}" and said["version"] == f"0.{i + 1}" and said["dep"] is None
        assert said["pipelines"] == [f"p0{i + 1}"] and said["argv"] == ["run", "x"]
        assert Path(str(said["file"])).resolve().is_relative_to(cache / "revs" / sha / "src")
    assert not (cache / "envs" / revisions[0].command[0].split("/")[-3] / "lib").joinpath("slamreplay").exists()
    again = prepare_revision(repo, shas[1], cache, note=(notes := []).append)
    assert notes == [f"using the environment of {shas[1][:10]} built before ({cache / 'revs' / shas[1]})"]
    assert again.command == revisions[1].command


def test_changed_dependencies_get_a_second_environment(project: tuple[Path, list[str]], tmp_path: Path) -> None:
    """A commit that adds a dependency gets its own environment, built once, with that dependency in it."""
    repo, shas = project
    cache = tmp_path / "cache"
    first, last = prepare_revision(repo, shas[2], cache), prepare_revision(repo, shas[3], cache)
    envs = sorted(p.name for p in (cache / "envs").iterdir() if p.is_dir())
    assert len(envs) == 2 and first.command[0] != last.command[0]
    assert cli(last)["dep"] == 7 and cli(first)["dep"] is None
    spec = json.loads((Path(last.command[0]).parents[1] / "spec.json").read_text())
    assert spec["dependencies"] == [f"tinydep @ {(tmp_path / 'tinydep-1.0-py3-none-any.whl').as_uri()}"]


def test_environment_that_does_not_build_is_removed(project: tuple[Path, list[str]], tmp_path: Path) -> None:
    """A dependency pip cannot find: one error naming the step and the log, no environment nor worktree left."""
    repo, _ = project
    (repo / "pyproject.toml").write_text(pyproject("0.5", ["no-such-dist-x"]))
    git(repo, "commit", "-qam", "a dependency nowhere")
    cache = tmp_path / "cache"
    with pytest.raises(ReplayError, match=r"does not build: `pip install` failed; see .*failed-build\.log"):
        prepare_revision(repo, "HEAD", cache)
    assert [p for p in (cache / "envs").iterdir() if p.is_dir()] == []
    assert [p for p in (cache / "revs").iterdir() if p.is_dir()] == []
    assert len(git(repo, "worktree", "list").splitlines()) == 1


def test_prepare_prunes_to_the_limit_but_not_what_is_in_use(project: tuple[Path, list[str]], tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Over $SLAMREPLAY_CACHE_LIMIT_GB, preparing a revision removes the least recently used ones not in use."""
    repo, shas = project
    cache = tmp_path / "cache"
    old = prepare_revision(repo, shas[0], cache)
    prepare_revision(repo, shas[1], cache)  # released at once: free to prune
    monkeypatch.setenv("SLAMREPLAY_CACHE_LIMIT_GB", "1K")
    prepare_revision(repo, shas[2], cache)
    left = sorted(p.name for p in (cache / "revs").iterdir() if p.is_dir())
    assert left == sorted([shas[0], shas[2]])  # shas[0] held by `old`, shas[2] by the call itself while it ran
    assert {e.name for e in rev_cache.entries(cache) if e.in_use} == {shas[0], old.command[0].split("/")[-3]}
    assert len(git(repo, "worktree", "list").splitlines()) == 3  # the pruned worktree is gone from git too
