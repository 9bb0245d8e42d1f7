"""Change detection over a history: known steps found where they are, flat metrics never flagged."""

from __future__ import annotations

import numpy as np
import pytest

from slamreplay.replay.runs.changepoints import find_steps, noise_sigma


def history(n: int, rng: np.random.Generator, sigma: float = 0.02, seeds: int = 3,
            steps: dict[int, float] | None = None) -> list[dict[int, float]]:
    """n commits of a metric near 1.0: a fixed offset per seed (its world), fresh noise per commit and seed,
    and the level moving by ``steps[k]`` from commit k on."""
    offset = rng.normal(0, 5 * sigma, seeds)
    level, out = 1.0, []
    for k in range(n):
        level += (steps or {}).get(k, 0.0)
        out.append({s: float(level + offset[s] + rng.normal(0, sigma)) for s in range(seeds)})
    return out


@pytest.mark.parametrize("seed", range(5))
def test_flat_noisy_history_has_no_change(seed: int) -> None:
    """40 commits of seed noise around one level: no change, in any direction convention."""
    values = history(40, np.random.default_rng(seed))
    for better in ("lower", "higher", "none"):
        assert find_steps(values, better, 1e-6, 1e-3) == []


def test_deterministic_history_never_flagged() -> None:
    """Replays are deterministic: 200 identical commits (and float jitter within tolerance) are no change."""
    values = [{0: 0.5, 1: 0.7, 2: 0.6}] * 200
    assert noise_sigma([0.5] * 200) == 0.0 and find_steps(values, "lower", 1e-6, 1e-3) == []
    jitter = [{s: v * (1 + 1e-7 * (k % 3)) for s, v in p.items()} for k, p in enumerate(values)]
    assert find_steps(jitter, "lower", 1e-6, 1e-3) == []


def test_step_up_and_back_found_with_directions() -> None:
    """A rise at 12 and a fall back at 25 (5 sigma of the per-seed noise) are the two changes, judged by the
    metric's direction."""
    values = history(36, np.random.default_rng(7), steps={12: 0.1, 25: -0.1})
    worse_up = find_steps(values, "lower", 1e-6, 1e-3)
    assert [(s.index, s.before, s.verdict) for s in worse_up] == [(12, 11, "regression"), (25, 24, "improvement")]
    assert worse_up[0].delta == pytest.approx(0.1, abs=0.03) and worse_up[0].p_value is not None
    assert [s.verdict for s in find_steps(values, "higher", 1e-6, 1e-3)] == ["improvement", "regression"]
    assert [s.verdict for s in find_steps(values, "none", 0.0, 0.0)] == ["changed", "changed"]


def test_target_metric_judged_by_distance() -> None:
    """A NEES (target 2) moving from 2.1 to 4 is worse; from 4 back to 2.1 better."""
    values = [{0: v, 1: v * 1.05, 2: v * 0.95} for v in [2.1] * 6 + [4.0] * 6 + [2.1] * 6]
    assert [(s.index, s.verdict) for s in find_steps(values, "target", 1e-6, 1e-3, 2.0)] == [
        (6, "regression"), (12, "improvement")]


def test_seed_inconsistent_or_tiny_change_not_flagged() -> None:
    """A shift whose sign differs between seeds is seed noise; a consistent one within tolerance is no change."""
    mixed = [{0: 1.0, 1: 2.0, 2: 3.0}] * 10 + [{0: 1.3, 1: 1.7, 2: 3.05}] * 10
    assert find_steps(mixed, "lower", 1e-6, 1e-3) == []
    tiny = [{0: 1.0, 1: 2.0}] * 10 + [{0: 1.0005, 1: 2.0005}] * 10
    assert find_steps(tiny, "lower", 1e-6, 1e-3) == []
    assert [s.index for s in find_steps(tiny, "lower", 0.0, 0.0)] == [10]


def test_failed_commits_skipped() -> None:
    """Commits without a succeeded run are gaps: a change after one is named by the commit with data before it."""
    values: list[dict[int, float]] = [{0: 1.0, 1: 1.1}] * 5 + [{}] * 2 + [{0: 1.5, 1: 1.6}] * 5
    (step,) = find_steps(values, "lower", 1e-6, 1e-3)
    assert (step.index, step.before, step.verdict) == (7, 4, "regression")
    assert find_steps([{}, {0: 1.0}], "lower") == []


def test_short_histories_judged_as_compare_judges_two_revisions() -> None:
    """Two or three commits: a consistent shift is a change (as compare would call it), an inconsistent one not."""
    two = [{0: 1.0, 1: 2.0, 2: 3.0}, {0: 1.2, 1: 2.21, 2: 3.19}]
    assert [(s.index, s.verdict) for s in find_steps(two, "lower", 1e-6, 1e-3)] == [(1, "regression")]
    three = [two[0], two[0], two[1]]
    assert [s.index for s in find_steps(three, "lower", 1e-6, 1e-3)] == [2]
    assert find_steps([two[0], {0: 1.2, 1: 1.8, 2: 3.1}], "lower", 1e-6, 1e-3) == []
