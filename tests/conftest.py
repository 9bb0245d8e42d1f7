"""Shared fixtures: where the public datasets are, and golden-file updates."""

from __future__ import annotations

import os
import shutil
import textwrap
from pathlib import Path

import pytest
from hypothesis import settings

REPO = Path(__file__).resolve().parents[1]

# Property tests draw the same examples on every run (a red CI names a real bug, not a new draw);
# HYPOTHESIS_PROFILE=explore draws fresh ones, to look for bugs on purpose.
settings.register_profile("repeatable", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "repeatable"))


@pytest.fixture(autouse=True)
def _no_declared_pipelines(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test starts without $SLAMREPLAY_PIPELINES and leaves none behind: a suite with ``declarations`` adds
    its files to the process's environment (for the workers it starts), which would leak into the next test of
    the same worker. setenv records the variable's absence; its undo, last, removes whatever a test set."""
    monkeypatch.setenv("SLAMREPLAY_PIPELINES", "")
    monkeypatch.delenv("SLAMREPLAY_PIPELINES")


@pytest.fixture(scope="session")
def _session_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("slamreplay-cache")


@pytest.fixture(autouse=True)
def _own_cache(monkeypatch: pytest.MonkeyPatch, _session_cache: Path) -> None:
    """Tests never read or write the user's ~/.cache/slamreplay (one cache per test process, so simulated
    recordings are still made once), and each test starts knowing no program's determinism (a verdict another
    test left would change how many times a program runs)."""
    monkeypatch.setenv("SLAMREPLAY_CACHE", str(_session_cache))
    shutil.rmtree(_session_cache / "determinism", ignore_errors=True)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--update-golden", action="store_true", help="rewrite tests/golden/ from this run")


def shared_data_root() -> Path:
    """The public datasets: $SLAMREPLAY_DATA, else ../shared/data beside the checkout."""
    return Path(os.environ.get("SLAMREPLAY_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture
def shared_data() -> Path:
    """Root of ../shared/data; skips the test with a reason when it is absent (a user's clone)."""
    root = shared_data_root()
    if not root.is_dir():
        pytest.skip(f"public datasets not found at {root} (set SLAMREPLAY_DATA); CI has them, a clone does not")
    return root


@pytest.fixture
def update_golden(request: pytest.FixtureRequest) -> bool:
    return bool(request.config.getoption("--update-golden"))


def write_tiny_recording(path: Path, n: int = 100, *, drift: float = 0.05, seed: int = 0,
                         perturb: float = 0.0) -> Path:
    """A small synthetic recording: a robot on an arc, odometry with a scale/heading drift,
    ground truth at the same times, a landmark map and range-bearing scans with true ids.
    ``perturb`` scales odometry and ranges by ``1 + perturb`` (numerical noise, e.g. 1e-12)."""
    import numpy as np

    from slamreplay.recorder import GroundTruthPose, LandmarkMap, OdometryPose, RangeBearingScan, Recorder

    rng = np.random.default_rng(seed)
    landmarks = np.array([[2.0, 1.0], [3.0, -1.0], [5.0, 2.0], [1.0, 3.0]])
    with Recorder(path, source={"test": "tiny"}, seed=seed) as rec:
        rec.write("/ground_truth/landmarks", LandmarkMap(1_000_000_000, np.arange(4), landmarks))
        x = np.zeros(3)
        o = np.zeros(3)
        for k in range(n):
            t = 1_000_000_000 + k * 100_000_000
            rec.write("/ground_truth/pose", GroundTruthPose(t, *x))
            rec.write("/odom", OdometryPose(t, o[0] * (1 + perturb), o[1] * (1 + perturb), o[2]))
            if k % 5 == 0:
                d = landmarks - x[:2]
                r = np.hypot(d[:, 0], d[:, 1]) + rng.normal(0, 0.01, 4)
                b = np.arctan2(d[:, 1], d[:, 0]) - x[2]
                rec.write("/landmarks/range_bearing",
                          RangeBearingScan(t, r * (1 + perturb), b, np.arange(4), 0.01, 0.01))
            v, w = 0.1, 0.02
            x = x + [v * np.cos(x[2]), v * np.sin(x[2]), w]
            o = o + [(1 + drift) * v * np.cos(o[2]), (1 + drift) * v * np.sin(o[2]), w * (1 + drift)]
    return path


@pytest.fixture
def tiny_recording(tmp_path: Path) -> Path:
    """A 100-step synthetic recording with odometry, ground truth, scans and a landmark map."""
    return write_tiny_recording(tmp_path / "tiny.mcap")


@pytest.fixture(scope="session")
def pipeline_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One run directory per built-in pipeline on short seeded simulations (tests/replay/view_runs.py),
    made once per session: the golden metrics and the view tests share them."""
    from tests.replay.view_runs import make_runs

    return make_runs(tmp_path_factory.mktemp("pipeline-runs"))


def make_distribution(root: Path, name: str, version: str, entry_points: dict[str, str],
                      modules: dict[str, str], group: str = "slamreplay.pipelines") -> None:
    """An installed distribution as importlib.metadata sees one: a .dist-info folder and modules on sys.path."""
    info = root / f"{name.replace('-', '_')}-{version}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
    lines = [f"[{group}]", *(f"{k} = {v}" for k, v in entry_points.items())]
    (info / "entry_points.txt").write_text("\n".join(lines) + "\n")
    for module, source in modules.items():
        path = root / (module.replace(".", "/") + ".py")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(source))
