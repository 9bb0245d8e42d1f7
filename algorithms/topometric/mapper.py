"""Incremental topo-metric mapping: locations linked by odometry, closed by visual loop closures.

Section III-A of Battesti, Bazeille, Filliat (ECMR 2011) [1]_: an image is taken each time the robot
has moved 50 cm or turned 10 degrees; each image either adds a location, linked to the previous one
by the relative odometry, or, when a loop closure is detected and validated, *updates* the matched
location (its words gain the image's) and adds a loop edge to it, after which the graph is relaxed
[2]_. Detection is two-level: the Bayes filter over locations (:mod:`.bayes`) proposes the locations
whose posterior exceeds ``candidate_threshold``; each is validated by the 2D motion of
:mod:`.validation`, and among the accepted ones the one with the smallest translation wins
(section III-A). A loop edge says "the robot is at the matched location, turned by the image
x-translation": from the previous location, its measurement is the odometry since the previous
image followed by the heading deviation ``delta = tx_px * hfov / width`` (section IV-B's linear rule,
as navigation reads it; tx > 0: the robot points left of the location's heading), so the matched
location's pose is the current one turned by ``-delta``. Its covariance is that odometry's plus the
image's, anisotropic in the matched location's frame: ``loop_sigma_along_m`` along its view
direction (an image scale cannot give a distance without depth), ``loop_sigma_xy_m`` across it and
``loop_sigma_theta_deg`` on the heading.
An edge that leaves a location the previous image closed a loop with starts from the robot's
heading there (the location's plus that image's deviation) and carries that image's covariance too,
in the location's frame: the robot was only near the location.

The relaxation uses the project's pose-graph back end (Gauss-Newton, incremental; [2]_ used TORO)
without robust kernel by default, as the paper: validated loop closures are trusted (its first concern
is that none is false). Beyond the paper, ``relax_robust="dcs"`` makes each relaxation a batch solve
(:func:`slamreplay.algorithms.common.posegraph.optimize`) with Dynamic Covariance Scaling [3]_ on the
loop edges only, then a chi-square gate at its solution. A loop edge the gate drops is *rejected*: the
mapper reports it (:meth:`TopoMetricMapper.rejected`), the map for navigation leaves it out, and each
relaxation decides again over every loop edge, so a closure rejected early can come back once later
ones confirm it. Repeated wall panels make whole runs of consecutive loop closures false (matched
along a look-alike corridor): the edges between the matched locations agree with the map, only the
way in and out does not. So with the kernel, an edge for an image after a loop-closing one starts
from the last location *created* (the anchor), by the odometry since the anchor's image, instead of
from the previous image's location: every closure of a run is weighed against the odometry on its
own, and the location created after a rejected run still hangs on the odometry, not on the
look-alike place.

References
----------
.. [1] E. Battesti, S. Bazeille, D. Filliat, "Qualitative localization using vision and odometry for
   path following in topo-metric maps", ECMR 2011, section III.
.. [2] S. Bazeille, D. Filliat, "Incremental topo-metric SLAM using vision and robot odometry", ICRA 2011.
.. [3] P. Agarwal, G. D. Tipaldi, L. Spinello, C. Stachniss, W. Burgard, "Robust map optimization using
   dynamic covariance scaling", ICRA 2013.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.posegraph import OptimizerConfig, PoseGraph, chi2, optimize
from slamreplay.algorithms.common.posegraph_incremental import IncrementalConfig, IncrementalOptimizer
from slamreplay.algorithms.common.robust import Kernel
from slamreplay.algorithms.topometric.bayes import FilterStep, LocationFilter
from slamreplay.algorithms.topometric.config import MapperConfig
from slamreplay.algorithms.topometric.features import FeatureExtractor, Features
from slamreplay.algorithms.topometric.topomap import TopoMap
from slamreplay.algorithms.topometric.validation import Validation, validate
from slamreplay.algorithms.topometric.vocabulary import Vocabulary

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class StepStatus(enum.Enum):
    """What the mapper did with one (image, odometry) pair."""

    SKIPPED = "skipped"  # not enough motion since the last image taken
    NO_FEATURES = "no_features"  # taken but blank / featureless: no location, no match
    NEW_LOCATION = "new_location"
    LOOP_CLOSURE = "loop_closure"


@dataclass(frozen=True, slots=True, eq=False)
class Candidate:
    """A potential loop closure: location, its posterior, and its validation."""

    location: int
    probability: float
    validation: Validation


@dataclass(frozen=True, slots=True, eq=False)
class Relaxation:
    """The location graph around one relaxation: poses (n, 3) before and after, chi2 before and after.

    ``rejected`` : (m,) bool per edge after it, the edges the robust relaxation dropped (all False
    without a kernel); ``chi2_after`` is over the kept edges.
    """

    poses_before: F64
    poses_after: F64
    chi2_before: float
    chi2_after: float
    iterations: int
    rejected: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))


@dataclass(frozen=True, slots=True, eq=False)
class MapperStep:
    """Result of :meth:`TopoMetricMapper.step`.

    Attributes
    ----------
    status : StepStatus.
    image_index : index among taken images (-1 when skipped).
    location : location of the image (new or matched; -1 when skipped or featureless).
    features : keypoints of the image (working resolution), None when skipped.
    filter : prior, likelihood and posterior over the locations before this image (+ "new").
    candidates : validated candidates, most probable first.
    accepted : the accepted loop closure, if any.
    relaxation : the relaxation it triggered, if any.
    edge : index of the edge this image added, or for a loop closure with the location the previous
        image closed with (no new edge), the edge that brought the robot there; -1 when none.
    durations_s : seconds of features, bow, filter, validation, relaxation (only with a clock).
    """

    status: StepStatus
    image_index: int = -1
    location: int = -1
    features: Features | None = None
    filter: FilterStep | None = None
    candidates: tuple[Candidate, ...] = ()
    accepted: Candidate | None = None
    relaxation: Relaxation | None = None
    edge: int = -1
    durations_s: dict[str, float] = field(default_factory=dict)


class TopoMetricMapper:
    """Mapping mode: incremental dictionary, new locations, loop closures, relaxation.

    Parameters
    ----------
    cfg : MapperConfig
    rng : the generator of the RANSAC samples (seeded by the caller).
    first_pose : (3,) map-frame pose of the first location.
    clock : optional seconds counter (e.g. ``time.perf_counter``) to fill ``durations_s``; the
        algorithm never reads a clock of its own.
    """

    def __init__(self, cfg: MapperConfig, rng: np.random.Generator, first_pose: ArrayLike = (0.0, 0.0, 0.0),
                 clock: Callable[[], float] | None = None) -> None:
        self.cfg = cfg
        self.rng = rng
        self.clock = clock
        self.extractor = FeatureExtractor(cfg.features)
        self.vocabulary = Vocabulary(cfg.vocabulary)
        self.filter = LocationFilter(cfg.filter)
        self._first_pose = np.asarray(first_pose, np.float64).reshape(3)
        self._robust_relax = cfg.relax_robust != "none"
        # robust: the incremental optimizer only places new locations; each relaxation is a batch solve
        iters = 0 if self._robust_relax else cfg.relax_iterations
        opt = OptimizerConfig(method="gn", max_iterations=iters, kernel=Kernel.NONE, rel_tol=1e-6)
        # skip_chi2 0: relax at every loop closure (section III), not only once the closures' chi2 debt mounts
        self._graph = IncrementalOptimizer(IncrementalConfig(optimizer=opt, skip_chi2=0.0), self._first_pose)
        self._features: list[Features] = []
        self._n_images: list[int] = []
        self._created: list[int] = []  # taken-image index that created each location
        self._loop: list[bool] = []
        self._rejected = np.zeros(0, bool)  # per edge: dropped by the last robust relaxation
        self._prev_edge = -1  # the edge that brought the robot to the previous image's location
        self._anchor: tuple[int, F64] | None = None  # the last location created, with the odometry at its image
        self._metric: bool | None = None
        self._sampled: F64 | None = None  # odometry at the last image taken
        self._processed: F64 | None = None  # odometry at the last image with features
        self._prev_location = -1
        self._prev_deviation: float | None = None  # the last image closed a loop: its heading deviation (rad)
        self._taken = 0
        self._since_loop = 0.0  # metres driven since the last loop closure (for the gate)

    # -- state ------------------------------------------------------------------------
    @property
    def n_locations(self) -> int:
        return len(self._features)

    @property
    def poses(self) -> F64:
        """(n, 3) current (relaxed) location poses in the map frame."""
        return self._graph.poses[: self.n_locations] if self.n_locations else np.zeros((0, 3))

    def edges(self) -> tuple[I64, I64, NDArray[np.bool_]]:
        """Edge endpoints (i, j) and whether each is a loop edge."""
        g = self._graph.graph
        return g.i.copy(), g.j.copy(), np.array(self._loop, bool)

    def rejected(self) -> NDArray[np.bool_]:
        """(m,) bool per edge: dropped by the latest robust relaxation (all False with ``relax_robust="none"``)."""
        out = np.zeros(len(self._loop), bool)
        out[: self._rejected.size] = self._rejected
        return out

    def topomap_features(self, location: int) -> Features:
        """Keypoints of a location's reference image (the one candidates are validated against)."""
        return self._features[location]

    def topomap(self) -> TopoMap:
        """The map for navigation (a snapshot; the mapper may go on); rejected edges are left out."""
        g = self._graph.graph
        keep = ~self.rejected()
        hists = [self.vocabulary.location_histogram(k) for k in range(self.n_locations)]
        return TopoMap.build(self.cfg, self.poses, g.i[keep], g.j[keep], g.measurements[keep], g.information[keep],
                             np.array(self._loop, bool)[keep], self._features, hists, self.vocabulary.words,
                             np.array(self._n_images, np.int64))

    # -- one step ---------------------------------------------------------------------
    def step(self, image: NDArray[np.generic], odom_pose: ArrayLike | None) -> MapperStep:
        """Process one image with the cumulative odometry pose at its time (None: no odometry).

        Without odometry every image is taken, edges carry no metric information and the graph is
        never relaxed; the filter uses its graph-neighbourhood model. The choice is fixed by the
        first call.
        """
        metric = odom_pose is not None
        if self._metric is None:
            self._metric = metric
        elif self._metric != metric:
            raise ValueError("odom_pose: give it at every step or at none")
        odom = None if odom_pose is None else np.asarray(odom_pose, np.float64).reshape(3)
        if odom is not None and not self._take(odom):
            return MapperStep(StepStatus.SKIPPED)
        self._sampled = odom
        k = self._taken
        self._taken += 1
        dur: dict[str, float] = {}
        tic = self._tic()
        feats = self.extractor.extract(image)
        tic = self._toc(dur, "features", tic)
        if len(feats) == 0:
            return MapperStep(StepStatus.NO_FEATURES, k, -1, feats, durations_s=dur)
        words, counts = Vocabulary.histogram(self.vocabulary.quantize(feats.descriptors, learn=True))
        scores = self.vocabulary.scores(words, counts)
        tic = self._toc(dur, "bow", tic)
        n = self.n_locations
        # Angeli et al.: the locations created from the last images look like the current one; a
        # re-visited location stays eligible (it is validated against its old reference image)
        eligible = np.array(self._created, np.int64) < k - self.cfg.recent_images
        motion = None
        if odom is not None and self._processed is not None:
            motion = se2.between(self._processed, odom)
        elif odom is not None:
            motion = np.zeros(3)
        if motion is not None and n and self.cfg.odometry_gate:
            eligible &= self._gate(motion)
        g = self._graph.graph
        fstep = self.filter.step(self.poses, motion, scores, eligible.reshape(n), (g.i, g.j))
        tic = self._toc(dur, "filter", tic)
        cands, best = self._validate(feats, fstep.posterior, eligible)
        tic = self._toc(dur, "validation", tic)
        post = fstep.posterior.copy()
        relax = None
        if best is not None:
            loc = best.location
            self.vocabulary.update_location(loc, words, counts)
            self._n_images[loc] += 1
            post[loc] += post[n]
            post[n] = 0.0
            edge, relax = self._add_edge(loc, motion, self._deviation(best))
            if edge < 0 and loc == self._prev_location:
                edge = self._prev_edge  # still at the location the previous image closed with
            status = StepStatus.LOOP_CLOSURE
        else:
            loc = self.vocabulary.add_location(words, counts)
            self._features.append(feats)
            self._n_images.append(1)
            self._created.append(k)
            post = np.r_[post[:n], post[n], 0.0]
            edge, relax = self._add_edge(loc, motion, None) if loc > 0 else (-1, None)
            if odom is not None:
                self._anchor = (loc, odom)
            status = StepStatus.NEW_LOCATION
        self._toc(dur, "relaxation", tic)
        self.filter.commit(post)
        self._prev_location = loc
        self._prev_edge = edge
        self._prev_deviation = None if best is None else self._deviation(best)
        self._processed = odom
        if best is not None:
            self._since_loop = 0.0
        elif motion is not None:
            self._since_loop += math.hypot(motion[0], motion[1])
        return MapperStep(status, k, loc, feats, fstep, cands, best, relax, edge, dur)

    def _gate(self, motion: F64) -> NDArray[np.bool_]:
        """Locations within the drift bound of the current odometry estimate (MapperConfig gate_*)."""
        c = self.cfg
        here = se2.compose(self.poses[self._prev_location], motion)
        d = self._since_loop + math.hypot(motion[0], motion[1])
        dist = np.hypot(*(self.poses[:, :2] - here[:2]).T)
        turn = np.degrees(np.abs(se2.wrap_angle(self.poses[:, 2] - here[2])))
        ok: NDArray[np.bool_] = (dist <= c.gate_m + c.gate_m_per_m * d) & (turn <= c.gate_deg + c.gate_deg_per_m * d)
        return ok

    def _take(self, odom: F64) -> bool:
        if self._sampled is None:
            return True
        d = se2.between(self._sampled, odom)
        return bool(math.hypot(d[0], d[1]) >= self.cfg.sample_distance_m
                    or abs(math.degrees(float(d[2]))) >= self.cfg.sample_angle_deg)

    def _validate(self, feats: Features, posterior: F64, eligible: NDArray[np.bool_]
                  ) -> tuple[tuple[Candidate, ...], Candidate | None]:
        n = self.n_locations
        p = posterior[:n]
        idx = np.flatnonzero(eligible & (p >= self.cfg.candidate_threshold))
        idx = idx[np.argsort(-p[idx], kind="stable")][: self.cfg.max_candidates]
        w, h = self.cfg.features.width, self.cfg.features.height
        centre = ((w - 1) / 2.0, (h - 1) / 2.0)
        cands = tuple(Candidate(int(i), float(p[i]), validate(self._features[i], feats, self.cfg.validation,
                                                               self.rng, centre)) for i in idx)
        ok = [c for c in cands if c.validation.accepted]
        best = min(ok, key=lambda c: c.validation.motion.translation_px if c.validation.motion else 0.0,
                   default=None)
        return cands, best

    def _deviation(self, match: Candidate) -> float:
        """Heading of the current image minus the matched location's: ``tx_px * hfov / width`` (IV-B)."""
        m = match.validation.motion
        return 0.0 if m is None else m.tx_px * math.radians(self.cfg.hfov_deg) / self.cfg.features.width

    def _image_covariance(self, heading: float) -> F64:
        """(3, 3) covariance of "the robot is at a location" for a location with that heading in the edge frame."""
        c = self.cfg
        ca, sa = math.cos(heading), math.sin(heading)
        rot = np.array([[ca, -sa], [sa, ca]])
        cov = np.zeros((3, 3))
        cov[:2, :2] = rot @ np.diag([c.loop_sigma_along_m**2, c.loop_sigma_xy_m**2]) @ rot.T
        cov[2, 2] = math.radians(c.loop_sigma_theta_deg) ** 2
        return cov

    def _add_edge(self, loc: int, motion: F64 | None, deviation: float | None) -> tuple[int, Relaxation | None]:
        """Edge to ``loc`` for the current image; ``deviation`` (rad) when the image closed a loop with it.

        Returns the new edge's index (-1: none added) and the relaxation it triggered.

        The paper's structure: from the previous location by the odometry since the previous image. The
        robot was at the previous location only as closely as its image said when that image closed a
        loop (``self._prev_deviation`` not None): the edge then starts from the robot's heading there and
        carries that image's uncertainty too. With the robust relaxation, an edge for an image after a
        loop-closing one starts instead from the last location created (the anchor) by the odometry since
        its image, so every loop closure of a run is weighed on its own against the odometry.
        """
        prev = self._prev_location
        anchored = (self._robust_relax and self._metric and self._prev_deviation is not None
                    and self._anchor is not None and self._processed is not None and motion is not None)
        if anchored:
            assert self._anchor is not None and self._processed is not None and motion is not None
            prev, odom0 = self._anchor
            z = se2.between(odom0, se2.compose(self._processed, motion))
            cov = self._odometry_covariance(z)
        else:
            z = np.zeros(3) if motion is None else motion
            cov = self._odometry_covariance(z)
            if self._metric and motion is not None and self._prev_deviation is not None:
                z = se2.compose(np.array([0.0, 0.0, self._prev_deviation]), z)
                cov += self._image_covariance(0.0)
        if prev < 0 or prev == loc:
            return -1, None
        loop = deviation is not None
        if not (self._metric and motion is not None):
            cov = np.diag(np.full(3, 1e6))  # no odometry: the edge only records adjacency
        elif deviation is not None:
            z = se2.compose(z, np.array([0.0, 0.0, -deviation]))  # the location's heading: the robot's - delta
            cov += self._image_covariance(float(z[2]))
        before = self.poses
        res = self._graph.step([prev], [loc], z[None, :], np.linalg.inv(cov)[None])
        self._loop.append(loop)
        edge = len(self._loop) - 1
        if not loop or not self._metric:
            return edge, None
        g_before = self._graph.graph.with_poses(before)
        if not self._robust_relax:
            return edge, Relaxation(before, self.poses, chi2(g_before), res.chi2, res.iterations,
                                    np.zeros(edge + 1, bool))
        return edge, self._relax_robust(g_before)

    def _odometry_covariance(self, z: F64) -> F64:
        """(3, 3) covariance of an odometry displacement ``z``, growing with its length and turn."""
        c = self.cfg
        dist, turn = math.hypot(z[0], z[1]), abs(float(z[2]))
        sxy = c.odometry_sigma_floor + c.odometry_sigma_xy_m_per_m * dist
        sth = (c.odometry_sigma_floor + c.odometry_sigma_theta_rad_per_m * dist
               + c.odometry_sigma_theta_rad_per_rad * turn)
        return np.diag([sxy**2, sxy**2, sth**2])

    def _relax_robust(self, g_before: PoseGraph) -> Relaxation:
        """Batch DCS solve and chi-square gate over the loop edges, from the current estimate (2x the iterations:
        the kernel parameter is graduated first)."""
        c = self.cfg
        opt = OptimizerConfig(method="gn", max_iterations=2 * c.relax_iterations, kernel=Kernel.DCS, rel_tol=1e-6,
                              inlier_gate=c.relax_gate_probability)
        out = optimize(self._graph.graph, opt, robust=np.array(self._loop, bool))
        self._graph.set_poses(out.poses)
        self._rejected = ~out.inliers if out.inliers.size else np.zeros(g_before.n_edges, bool)
        return Relaxation(g_before.poses, self.poses, chi2(g_before), out.chi2_final, out.iterations,
                          self._rejected.copy())

    def _tic(self) -> float:
        return self.clock() if self.clock is not None else 0.0

    def _toc(self, dur: dict[str, float], name: str, tic: float) -> float:
        if self.clock is None:
            return 0.0
        now = self.clock()
        dur[name] = now - tic
        return now
