"""Discrete Bayes filter over map locations with a "new location" hypothesis.

The state is ``p = [p(L_0), ..., p(L_{n-1}), p(new)]``. Each processed image:

1. *Prediction* with the odometry evolution model of Bazeille and Filliat [1]_ as improved in
   [2]_ section III-B: for each of the last ``history`` time steps t-k, the posterior of t-k is moved
   by the odometry displacement from t-k to now: from location j the robot is predicted at
   ``pose_j (+) u``, and the mass of j goes to the locations around that pose with Gaussian weights
   (``sigma_xy_m``, ``sigma_theta_deg``), scaled by ``1 - p_new`` and normalised by ``max(sum, 1)``;
   the rest goes to "new" (a prediction that lands on no location is a new place). The K
   predictions are merged with ``max``; ineligible locations (mapping mode: seen in the last few
   images, which look like the current one but are no loop closure) hand their mass to "new";
   "new" keeps ``1 - p_new`` of it and spreads ``p_new`` uniformly over the eligible locations
   (Angeli et al. [3]_: a known place reached off the prediction), then all is normalised.
   Without odometry (``motion`` None) the
   model degenerates to the graph neighbourhood: mass spreads over locations within ``hops`` edges,
   with Gaussian weights in the hop count, from the previous step only.
2. *Update* with the likelihood of Angeli et al. [3]_ from the tf-idf scores ``s`` of the eligible
   locations (mean ``mu``, std ``sigma``): ``(s - sigma) / mu`` where ``s >= mu + sigma``, else 1;
   "new" gets 1.

References
----------
.. [1] S. Bazeille, D. Filliat, "Incremental topo-metric SLAM using vision and robot odometry", ICRA 2011.
.. [2] E. Battesti, S. Bazeille, D. Filliat, "Qualitative localization using vision and odometry for
   path following in topo-metric maps", ECMR 2011, section III-B.
.. [3] A. Angeli, D. Filliat, S. Doncieux, J.-A. Meyer, "Fast and incremental method for loop-closure
   detection using bags of visual words", IEEE T-RO 24(5), 2008.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from slamreplay.algorithms.common import se2

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class FilterConfig:
    """Attributes
    ----------
    p_new : probability of leaving the map for a new place in one step (Angeli's 0.1).
    sigma_xy_m, sigma_theta_deg : spread of the odometry evolution model: the map's sampling step
        (0.5 m / 10 deg) and the lateral offset of a revisit, not the odometry noise.
    history : K, the previous time steps whose predictions are merged with max (paper III-B).
    max_sources : at most this many most probable locations are propagated per time step.
    min_mass : locations below this probability are not propagated.
    hops : without odometry, the graph neighbourhood reached in one step.
    """

    p_new: float = 0.1
    sigma_xy_m: float = 0.4
    sigma_theta_deg: float = 20.0
    history: int = 3
    max_sources: int = 32
    min_mass: float = 1e-5
    hops: int = 2

    def __post_init__(self) -> None:
        if not 0.0 < self.p_new < 1.0:
            raise ValueError(f"p_new must be in (0, 1), got {self.p_new}")
        if not (self.sigma_xy_m > 0 and self.sigma_theta_deg > 0):
            raise ValueError("sigma_xy_m and sigma_theta_deg must be > 0")
        if self.history < 1 or self.max_sources < 1 or self.hops < 0:
            raise ValueError("history and max_sources must be >= 1, hops >= 0")
        if not 0.0 <= self.min_mass < 1.0:
            raise ValueError(f"min_mass must be in [0, 1), got {self.min_mass}")


@dataclass(frozen=True, slots=True, eq=False)
class FilterStep:
    """prior, likelihood, posterior: (n + 1,) over the n locations then "new"."""

    prior: F64
    likelihood: F64
    posterior: F64


def likelihood(scores: F64, eligible: B) -> F64:
    """Angeli's mu + sigma rule: (n + 1,) likelihoods, 1 for "new" and every non-distinctive location."""
    n = len(scores)
    out = np.ones(n + 1)
    s = scores[eligible]
    if s.size == 0:
        return out
    mu, sigma = float(s.mean()), float(s.std())
    if mu <= 0.0:
        return out
    hit = eligible & (scores >= mu + sigma) & (scores > sigma)
    out[:n][hit] = (scores[hit] - sigma) / mu
    return np.maximum(out, 1.0)


class LocationFilter:
    """The filter's state: the last ``history`` posteriors and the odometry since each."""

    def __init__(self, cfg: FilterConfig = FilterConfig(), initial: ArrayLike | None = None) -> None:
        self.cfg = cfg
        p = np.array([1.0] if initial is None else initial, np.float64).reshape(-1)
        if p.size < 1 or not np.all(p >= 0) or not p.sum() > 0:
            raise ValueError("initial must be a non-negative (n + 1,) vector with a positive sum")
        self._history: list[tuple[F64, F64]] = [(p / p.sum(), np.zeros(3))]

    @property
    def posterior(self) -> F64:
        """The latest committed posterior (n + 1,)."""
        return self._history[-1][0].copy()

    def step(self, poses: F64, motion: ArrayLike | None, scores: F64, eligible: B,
             edges: tuple[I64, I64] | None = None) -> FilterStep:
        """Predict with the evolution model, update with the scores; does not commit.

        Parameters
        ----------
        poses : (n, 3) location poses in the map frame (m, m, rad).
        motion : (3,) odometry displacement since the previous committed step, in the robot frame
            at that step; None without odometry (graph-neighbourhood model, needs ``edges``).
        scores : (n,) tf-idf scores of the current image.
        eligible : (n,) bool, locations that may be matched now.
        edges : (i, j) location graph edges, for the model without odometry.
        """
        n = len(poses)
        if scores.shape != (n,) or eligible.shape != (n,):
            raise ValueError(f"scores and eligible must be ({n},), got {scores.shape} and {eligible.shape}")
        if motion is not None:
            u = np.asarray(motion, np.float64).reshape(3)
            self._history = [(p, se2.compose(d, u)) for p, d in self._history]
            preds = [self._predict_odometry(self._pad(p, n), poses, d) for p, d in self._history]
        else:
            preds = [self._predict_graph(self._pad(self._history[-1][0], n), n, edges)]
        prior = np.max(preds, axis=0)
        prior[n] += prior[:n][~eligible].sum()
        prior[:n][~eligible] = 0.0
        m, n_eligible = prior[n], int(eligible.sum())
        if n_eligible:  # "new" is a place off the prediction: any eligible location, with p_new
            prior[:n][eligible] += self.cfg.p_new * m / n_eligible
            prior[n] = (1.0 - self.cfg.p_new) * m
        prior /= prior.sum()
        lik = likelihood(scores, eligible)
        post = prior * lik
        return FilterStep(prior, lik, post / post.sum())

    def commit(self, posterior: ArrayLike) -> None:
        """Record the step's final state (after the caller moved "new" into a created or matched location)."""
        p = np.array(posterior, np.float64).reshape(-1)
        if not (np.all(p >= 0) and p.sum() > 0):
            raise ValueError("posterior must be non-negative with a positive sum")
        self._history.append((p / p.sum(), np.zeros(3)))
        del self._history[: -self.cfg.history]

    @staticmethod
    def _pad(p: F64, n: int) -> F64:
        out = np.zeros(n + 1)
        m = len(p) - 1
        out[:m], out[n] = p[:m], p[m]
        return out

    def _sources(self, p: F64, n: int) -> I64:
        src = np.flatnonzero(p[:n] > self.cfg.min_mass)
        if src.size > self.cfg.max_sources:
            src = src[np.argsort(-p[src], kind="stable")[: self.cfg.max_sources]]
        return src

    def _spread(self, p: F64, n: int, src: I64, w: F64) -> F64:
        """Move the mass of ``src`` along weights w (len(src), n), the rest to "new"; "new" as Angeli."""
        cfg = self.cfg
        out = np.zeros(n + 1)
        keep = (1.0 - cfg.p_new) / np.maximum(w.sum(axis=1), 1.0)
        out[:n] = (p[src] * keep) @ w
        moved = out[:n].sum()
        out[n] = p[:n].sum() - moved + p[n]
        return out

    def _predict_odometry(self, p: F64, poses: F64, disp: F64) -> F64:
        n = len(poses)
        src = self._sources(p, n)
        if src.size == 0:
            return self._spread(p, n, src, np.zeros((0, n)))
        pred = se2.compose(poses[src], disp)
        d2 = ((pred[:, None, :2] - poses[None, :, :2]) ** 2).sum(axis=2)
        dth = se2.wrap_angle(pred[:, None, 2] - poses[None, :, 2])
        w = np.exp(-0.5 * (d2 / self.cfg.sigma_xy_m**2 + (dth / math.radians(self.cfg.sigma_theta_deg)) ** 2))
        return self._spread(p, n, src, w)

    def _predict_graph(self, p: F64, n: int, edges: tuple[I64, I64] | None) -> F64:
        src = self._sources(p, n)
        w = np.zeros((src.size, n))
        if src.size:
            if edges is not None and len(edges[0]):
                i, j = np.asarray(edges[0]), np.asarray(edges[1])
                adj = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
                hops = dijkstra(adj, directed=False, indices=src, unweighted=True, limit=self.cfg.hops + 0.5)
            else:
                hops = np.full((src.size, n), np.inf)
                hops[np.arange(src.size), src] = 0.0
            w = np.where(np.isfinite(hops), np.exp(-0.5 * np.nan_to_num(hops, posinf=0.0) ** 2), 0.0)
        return self._spread(p, n, src, w)
