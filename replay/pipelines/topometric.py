"""Pipeline ``topometric``: visual topo-metric mapping (Battesti, Bazeille, Filliat, ECMR 2011, section III).

Each ``/camera/image`` goes to :class:`~slamreplay.algorithms.topometric.TopoMetricMapper` with the latest
``/odom`` pose; the mapper takes an image every 50 cm or 10 degrees of odometry, adds a location or
closes a loop, and relaxes the graph at each loop closure. Logged: each taken image with its
keypoints (``camera/image``), each candidate as the map image beside the current one with inlier
and outlier matches and its 2D motion (``camera/candidate``), the filter's posterior over locations
(``topo/posterior``, plus ``metrics/posterior_*``), the graph (``world/graph/current``) and around
each relaxation ``world/graph/before`` and ``world/graph/after``, and the decisions as text
(``topo/log``). The map goes to ``map.npz`` (:mod:`slamreplay.replay.tools.topomap_io`); with ``/ground_truth/pose``
it also holds, for evaluation only, each location's true pose (that of its reference image,
interpolated at the image's log time; NaN outside the ground truth's time span) as ``truth_poses``:
``slamreplay navigate`` and ``topometric-nav`` score a drive against the route through these true
poses, as the paper compares the replay and the mapping trajectories (Fig. 4).

Truth for precision and recall (only with ``/ground_truth/pose``): two images show the *same place*
when their true positions are within ``same_place_m`` and their headings within ``same_place_deg``
(defaults 1 m and 20 degrees). A loop closure is correct when the current image and the matched
location's reference image (the one that created it, whose pose the location has and against which
candidates are validated) are the same place. An image *should* close a loop when it is the same place
as the reference image of a location the mapper may match, i.e. created before the mapper's
``recent_images`` window (indices counted as the mapper counts them); recall is the share of those
that did. Only taken images with keypoints are scored. Being the same place as an earlier
loop-closing image only does not count: the only location to close with would be that image's,
whose reference image is not the same place, so no correct loop closure exists (the log also gives
the recall under that looser rule).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Literal

import numpy as np
import rerun.blueprint as rrb

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.observe import Bars, Image, LineStrips, Points, Scalar, Segments, State, Text
from slamreplay.algorithms.topometric import Candidate, MapperConfig, MapperStep, StepStatus, TopoMetricMapper
from slamreplay.recorder.messages import (
    TOPIC_CAMERA_IMAGE,
    TOPIC_GROUND_TRUTH_POSE,
    TOPIC_ODOM,
    CameraImage,
    GroundTruthPose,
    OdometryPose,
)
from slamreplay.replay.engine import views
from slamreplay.replay.engine.pipeline import Pipeline, ReplayContext
from slamreplay.replay.engine.reader import Envelope
from slamreplay.replay.metric_registry import specs
from slamreplay.replay.tools.topomap_io import save_map

STAGES = ("features", "bow", "filter", "validation", "relaxation")


@dataclass(frozen=True, slots=True)
class TopometricConfig:
    """Parameters of the ``topometric`` pipeline (the rest are :class:`MapperConfig` defaults)."""

    sample_distance_m: float = field(default=0.5, metadata={"help": (
        "an image is taken each time odometry moved this far (m; the paper, III-A: 0.5)")})
    sample_angle_deg: float = field(default=10.0, metadata={"help": (
        "... or turned this much (degrees; the paper, III-A: 10)")})
    candidate_threshold: float = field(default=0.1, metadata={"help": (
        "a location whose filter posterior reaches this is a loop-closure candidate, validated by image geometry")})
    recent_images: int = field(default=10, metadata={"help": (
        "locations created from the last this many images are no loop-closure hypotheses; 0: none excluded")})
    history: int = field(default=3, metadata={"help": (
        "K: the odometry predictions of the last this many time steps are merged with max (paper III-B)")})
    word_radius_bits: int = field(default=48, metadata={"help": (
        "a BRIEF descriptor within this Hamming distance (of 256 bits) of its nearest word is that word, else new")})
    min_inliers: int = field(default=12, metadata={"help": (
        "a candidate needs at least this many descriptor matches and RANSAC inliers to be accepted")})
    max_translation_px: float = field(default=40.0, metadata={"help": (
        "a candidate whose image-to-image translation exceeds this (pixels) is rejected")})
    max_rotation_deg: float = field(default=8.0, metadata={"help": (
        "a candidate whose image-to-image rotation exceeds this (degrees) is rejected")})
    # why 1.10: algorithms/topometric/validation.py, ValidationConfig
    max_scale: float = field(default=1.10, metadata={"help": (
        "a candidate's image-to-image scale must lie in [1 / max_scale, max_scale]")})
    same_place_m: float = field(default=1.0, metadata={"help": (
        "scoring (precision, recall): images show the same place when their true positions are this close (m)")})
    same_place_deg: float = field(default=20.0, metadata={"help": (
        "... and their true headings this close (degrees)")})
    odometry_gate: bool = field(default=True, metadata={"help": (
        "beyond the paper: a location is a loop-closure hypothesis only within 2 m + 10 % of the distance "
        "driven since the last loop closure (and 30 deg + 0.5 deg/m) of the odometry estimate; false: off")})
    relax_robust: Literal["none", "dcs"] = field(default="none", metadata={"help": (
        "relaxation: none (the paper: plain least squares, every validated loop closure trusted) or dcs "
        "(beyond the paper: Dynamic Covariance Scaling and a chi-square gate on the loop edges; "
        "a closure it drops is rejected: not counted, drawn red, left out of the map)")})

    def __post_init__(self) -> None:
        if not (self.same_place_m > 0 and self.same_place_deg > 0):
            raise ValueError("same_place_m and same_place_deg must be > 0")
        self.mapper()  # validates the rest

    def mapper(self) -> MapperConfig:
        base = MapperConfig()
        return replace(base, sample_distance_m=self.sample_distance_m, sample_angle_deg=self.sample_angle_deg,
                       candidate_threshold=self.candidate_threshold, recent_images=self.recent_images,
                       odometry_gate=self.odometry_gate, relax_robust=self.relax_robust,
                       filter=replace(base.filter, history=self.history),
                       vocabulary=replace(base.vocabulary, word_radius_bits=self.word_radius_bits),
                       validation=replace(base.validation, min_inliers=self.min_inliers,
                                          max_translation_px=self.max_translation_px,
                                          max_rotation_deg=self.max_rotation_deg, max_scale=self.max_scale))


class TopometricPipeline(Pipeline):
    name = "topometric"
    summary = "topo-metric visual mapping: STAR+BRIEF bag of words, Bayes filter, 2-point RANSAC, relaxation"
    required_topics = (TOPIC_CAMERA_IMAGE, TOPIC_ODOM)
    optional_topics = (TOPIC_GROUND_TRUTH_POSE,)
    start_topic = TOPIC_ODOM
    Config = TopometricConfig
    # "paper": every extra over [Battesti, Bazeille, Filliat 2011, section III] off; ``preset_notes``
    # says per key what the extra does and why it exists.
    presets: ClassVar[dict[str, dict[str, Any]]] = {
        "paper": {"odometry_gate": False, "relax_robust": "none", "sample_distance_m": 0.5, "sample_angle_deg": 10.0},
    }
    preset_notes: ClassVar[dict[str, str]] = {
        "odometry_gate": "the paper validates every posterior candidate by its image geometry alone; the extra "
                         "drops candidates farther from the odometry estimate than a drift bound, because the "
                         "simulator's repeated wall panels give a geometrically perfect false match 8.9 m away",
        "relax_robust": "the paper relaxes the graph by plain least squares (TORO), trusting every validated "
                        "closure; the extra (dcs) down-weights and gates loop edges that contradict the "
                        "rest of the graph, so a false closure is rejected instead of bending the map",
        "sample_distance_m": "the paper: an image every 50 cm (section III-A); the default is the same",
        "sample_angle_deg": "the paper: an image every 10 degrees (section III-A); the default is the same",
    }
    # the relaxed locations' ATE is ape_rmse_m: they are the trajectory (replay.evaluate)
    metrics = specs("images", "locations", "loop_closures", "loop_closures_rejected", "loop_closure_precision",
                    "loop_closure_recall", "odometry_ate_rmse_m")

    def __init__(self, config: TopometricConfig, ctx: ReplayContext) -> None:
        super().__init__(config, ctx)
        self.start = ctx.T_world_start if ctx.T_world_start is not None else np.zeros(3)
        self.mapper = TopoMetricMapper(config.mapper(), ctx.rng, self.start, clock=time.perf_counter)
        self.odom0: np.ndarray | None = None
        self.odom: np.ndarray | None = None
        self.gray: list[np.ndarray] = []  # reference image of each location (for the candidate view)
        self.taken_t: list[int] = []  # stamps of images taken with features
        self.taken_odom: list[np.ndarray] = []
        self.taken_loc: list[int] = []
        self.taken_index: list[int] = []  # the mapper's image index (it also counts featureless images)
        self.taken_loop: list[bool] = []
        self.taken_edge: list[int] = []  # the mapper's edge of each taken image (MapperStep.edge)
        self.created_t: list[int] = []
        self.durations: dict[str, list[float]] = {k: [] for k in (*STAGES, "image")}
        self.t_gt: list[int] = []
        self.gt: list[np.ndarray] = []
        self.relaxations = 0
        self.truth_poses: np.ndarray | None = None  # (n, 3) per location, set by finish() with ground truth

    def step(self, env: Envelope) -> None:
        msg = env.msg
        if isinstance(msg, GroundTruthPose):
            self.t_gt.append(env.log_time_ns)
            self.gt.append(msg.xy_yaw)
        elif isinstance(msg, OdometryPose):
            if self.odom0 is None:
                self.odom0 = msg.xy_yaw
            self.odom = se2.compose(self.start, se2.between(self.odom0, msg.xy_yaw))
        elif isinstance(msg, CameraImage) and self.odom is not None:
            tic = time.perf_counter()
            res = self.mapper.step(msg.pixels, self.odom)
            if res.status is not StepStatus.SKIPPED:
                self.durations["image"].append(time.perf_counter() - tic)
                for k in STAGES:
                    self.durations[k].append(res.durations_s.get(k, 0.0))
                self._log(env, res)

    # -- logging ----------------------------------------------------------------------
    def _log(self, env: Envelope, res: MapperStep) -> None:
        obs = self.ctx.observer
        gray = self.mapper.extractor.prepare(env.msg.pixels)  # type: ignore[union-attr]
        obs.log("camera/image", Image(gray))
        obs.log("topo/status", State(res.status.value))
        if res.features is not None:
            obs.log("camera/image/keypoints", Points(res.features.xy, radius=2.0))
        if res.status is StepStatus.NO_FEATURES:
            obs.log("topo/log", Text(f"image {res.image_index}: no keypoints (blank or featureless): no location",
                                     "WARN"))
            return
        if res.status is StepStatus.NEW_LOCATION:
            self.gray.append(gray)
            self.created_t.append(env.log_time_ns)
        self.taken_t.append(env.log_time_ns)
        assert self.odom is not None
        self.taken_odom.append(self.odom)
        self.taken_loc.append(res.location)
        self.taken_index.append(res.image_index)
        self.taken_loop.append(res.status is StepStatus.LOOP_CLOSURE)
        self.taken_edge.append(res.edge)
        if res.filter is not None:
            post = res.filter.posterior
            n = len(post) - 1
            obs.log("topo/posterior", Bars(np.asarray(post, dtype=np.float64)))
            obs.log("metrics/posterior_new", Scalar(float(post[n])))
            obs.log("metrics/posterior_max_location", Scalar(float(post[:n].max()) if n else 0.0))
        for c in res.candidates:
            self._log_candidate(gray, res, c)
        if res.accepted is not None:
            m = res.accepted.validation.motion
            assert m is not None
            obs.log("topo/log", Text(
                f"image {res.image_index}: LOOP CLOSURE with location {res.location} "
                f"(p={res.accepted.probability:.2f}, {m.n_inliers} inliers, t=({m.tx_px:.1f}, {m.ty_px:.1f}) px, "
                f"rot {math.degrees(m.rotation_rad):.1f} deg, scale {m.scale:.3f})"))
        poses = self.mapper.poses
        i, j, loop = self.mapper.edges()
        obs.log("world/graph/current/nodes", Points(poses[:, :2], radius=0.1))
        obs.log("world/graph/current/edges", Segments(poses[i, :2], poses[j, :2]))
        rej = self.mapper.rejected()
        obs.log("world/graph/current/loops", Segments(poses[i[loop & ~rej], :2], poses[j[loop & ~rej], :2]))
        if self.config.relax_robust != "none":
            obs.log("world/graph/current/rejected", Segments(poses[i[rej], :2], poses[j[rej], :2]))
        obs.log("metrics/locations", Scalar(float(len(poses))))
        if res.relaxation is not None:
            self.relaxations += 1
            for tag, p in (("before", res.relaxation.poses_before), ("after", res.relaxation.poses_after)):
                keep = (i < len(p)) & (j < len(p))
                obs.log(f"world/graph/{tag}/nodes", Points(p[:, :2], radius=0.08))
                obs.log(f"world/graph/{tag}/edges", Segments(p[i[keep], :2], p[j[keep], :2]))
            n_rej = int(res.relaxation.rejected.sum())
            obs.log("topo/log", Text(f"relaxation {self.relaxations}: chi2 {res.relaxation.chi2_before:.4g} -> "
                                     f"{res.relaxation.chi2_after:.4g} ({res.relaxation.iterations} iterations)"
                                     + (f", {n_rej} loop edges rejected" if n_rej else "")))

    def _log_candidate(self, gray: np.ndarray, res: MapperStep, c: Candidate) -> None:
        obs = self.ctx.observer
        v = c.validation
        w = gray.shape[1]
        obs.log("camera/candidate", Image(np.hstack([self.gray[c.location], gray])))
        ref = self.mapper.topomap_features(c.location)
        cur = res.features
        assert cur is not None
        inl = v.motion.inliers if v.motion is not None else np.zeros(len(v.matches), bool)
        a = ref.xy[v.matches[:, 0]] if len(v.matches) else np.zeros((0, 2))
        b = cur.xy[v.matches[:, 1]] + [w, 0.0] if len(v.matches) else np.zeros((0, 2))
        obs.log("camera/candidate/inliers", Segments(a[inl], b[inl]))
        obs.log("camera/candidate/outliers", Segments(a[~inl], b[~inl]))
        motion = "no motion" if v.motion is None else (
            f"t=({v.motion.tx_px:.1f}, {v.motion.ty_px:.1f}) px, rot {math.degrees(v.motion.rotation_rad):.1f} deg, "
            f"scale {v.motion.scale:.3f}, {v.motion.n_inliers}/{len(v.matches)} inliers")
        obs.log("topo/log", Text(f"image {res.image_index}: candidate location {c.location} (p={c.probability:.2f}): "
                                 f"{v.status.value}; {motion}", "INFO" if v.accepted else "DEBUG"))

    # -- end --------------------------------------------------------------------------
    def kept_loops(self) -> np.ndarray:
        """(k,) bool per taken image: closed a loop whose edge the robust relaxation did not reject (its final
        decision)."""
        loop = np.asarray(self.taken_loop, bool)
        rej = self.mapper.rejected()
        edge = np.asarray(self.taken_edge, np.int64)
        dropped = np.zeros(loop.size, bool)
        dropped[edge >= 0] = rej[edge[edge >= 0]]
        return loop & ~dropped

    def trajectory(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The relaxed locations, each at the time of the image that created it (what ``ape_rmse_m``
        scores); None before the first location."""
        created = np.flatnonzero(~np.asarray(self.taken_loop, bool))
        if not len(created):
            return None
        locs = np.asarray(self.taken_loc, np.int64)[created]
        return np.asarray(self.taken_t, np.int64)[created], np.asarray(self.mapper.poses, np.float64)[locs]

    def finish(self) -> dict[str, float]:
        n_img = len(self.durations["image"])
        kept = self.kept_loops()
        loops, n_rej = int(kept.sum()), int(sum(self.taken_loop)) - int(kept.sum())
        metrics: dict[str, float] = {"images": float(n_img), "locations": float(self.mapper.n_locations),
                                     "loop_closures": float(loops)}
        if self.config.relax_robust != "none":
            metrics["loop_closures_rejected"] = float(n_rej)
            i, j, _ = self.mapper.edges()
            rej = self.mapper.rejected()
            for q in np.flatnonzero(np.asarray(self.taken_loop, bool) & ~kept):
                e = self.taken_edge[q]
                self.ctx.log(f"rejected by the robust relaxation: image {self.taken_index[q]} -> location "
                             f"{self.taken_loc[q]} (edge {int(i[e])} -> {int(j[e])})")
            what = ", ".join(f"{int(a)}->{int(b)}" for a, b in zip(i[rej], j[rej], strict=True))
            self.ctx.log(f"robust relaxation: {int(rej.sum())} loop edges rejected ({what}), {n_rej} "
                         f"loop-closing images not counted")
        self.ctx.log(f"{n_img} images, {self.mapper.n_locations} locations, {loops} loop closures, "
                     f"{self.mapper.vocabulary.n_words} words")
        if len(self.gt) < 2 or not self.taken_t:
            self.ctx.log("no ground truth: precision, recall and ATE do not apply; the map has no truth_poses")
            return metrics
        t_gt = np.asarray(self.t_gt, np.int64)
        t = np.asarray(self.taken_t, np.int64)
        inside = (t >= t_gt[0]) & (t <= t_gt[-1])
        if inside.sum() < 2:
            self.truth_poses = np.full((self.mapper.n_locations, 3), np.nan)
            return metrics
        truth = se2.interpolate((t - t_gt[0]).astype(float), (t_gt - t_gt[0]).astype(float), np.array(self.gt))
        self.truth_poses = self._location_truth(truth, inside)
        self.ctx.observer.log("world/trajectory/truth", LineStrips((truth[inside, :2],)))
        metrics.update(self._loop_scores(truth, inside))
        created = np.flatnonzero(~np.asarray(self.taken_loop))
        ok = inside[created]
        odo = np.asarray(self.taken_odom)[created][ok, :2]
        tru = truth[created][ok, :2]
        metrics["odometry_ate_rmse_m"] = float(np.sqrt(np.mean(np.sum((odo - tru) ** 2, axis=1))))
        self.ctx.observer.log("world/trajectory/odometry", LineStrips((np.asarray(self.taken_odom)[:, :2],)))
        return metrics

    def _location_truth(self, truth: np.ndarray, inside: np.ndarray) -> np.ndarray:
        """(n, 3) true pose of each location's reference image (the taken image that created it), NaN outside."""
        out = np.full((self.mapper.n_locations, 3), np.nan)
        for q in np.flatnonzero(~np.asarray(self.taken_loop)):
            if inside[q]:
                out[self.taken_loc[q]] = truth[q]
        return out

    def _loop_scores(self, truth: np.ndarray, inside: np.ndarray) -> dict[str, float]:
        """Precision and recall by the same-place rule of the module docstring."""
        cfg = self.config
        k = len(truth)
        d = np.hypot(truth[:, None, 0] - truth[None, :, 0], truth[:, None, 1] - truth[None, :, 1])
        dth = np.abs(se2.wrap_angle(truth[:, None, 2] - truth[None, :, 2]))
        same = (d <= cfg.same_place_m) & (dth <= math.radians(cfg.same_place_deg))
        same &= inside[:, None] & inside[None, :]
        index = np.asarray(self.taken_index, np.int64)
        earlier = index[None, :] < index[:, None] - cfg.recent_images
        loop = self.kept_loops()
        ref_img = {loc: idx for idx, loc in reversed(list(enumerate(self.taken_loc)))}  # first image of a location
        is_ref = np.zeros(k, bool)
        is_ref[list(ref_img.values())] = True
        should = (same & earlier & is_ref[None, :]).any(axis=1)
        loose = (same & earlier).any(axis=1)
        correct = np.array([same[q, ref_img[self.taken_loc[q]]] for q in np.flatnonzero(loop)], bool)
        out: dict[str, float] = {}
        if loop.any():
            out["loop_closure_precision"] = float(correct.mean())
            for q in np.flatnonzero(loop)[~correct]:
                self.ctx.log(f"false loop closure: image {q} -> location {self.taken_loc[q]}")
        if should.any():
            out["loop_closure_recall"] = float((loop & should).sum() / should.sum())
        n_ok = int(correct.sum()) if loop.any() else 0
        self.ctx.log(f"same-place truth: {int(should.sum())} images should close a loop, {int(loop.sum())} did, "
                     f"{n_ok} correctly; same place as any earlier image: {int(loose.sum())} "
                     f"(recall {(loop & loose).sum() / max(int(loose.sum()), 1):.3f} by that rule)")
        return out

    def timings(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for k, v in self.durations.items():
            if v:
                out[f"{k}_mean_s"] = float(np.mean(v))
        if self.durations["image"]:
            out["image_max_s"] = float(np.max(self.durations["image"]))
        return out

    def artifacts(self) -> dict[str, bytes]:
        topomap = self.mapper.topomap()
        if self.truth_poses is not None and len(self.truth_poses) == topomap.n_locations:
            topomap = replace(topomap, truth_poses=self.truth_poses)
        return {"map.npz": save_map(topomap)}

    summary_skip = (*views.SUMMARY_SKIP, "graph/before", "graph/after")

    @classmethod
    def blueprint(cls, bounds: views.Bounds | None = None) -> rrb.Blueprint:
        posterior = ("metrics/posterior_new", "metrics/posterior_max_location")
        return views.layout(
            views.summary_tab(bounds, posterior, "Posterior: new location vs best known location"),
            views.tab("Loop closure",
                      rrb.Vertical(views.image_view("Current image and keypoints", "/camera/image"),
                                   views.image_view("Candidate: map location | current; inliers green, outliers red",
                                                    "/camera/candidate")),
                      rrb.Vertical(rrb.BarChartView(name="Posterior over locations (last bar: a new location)",
                                                    origin="/topo/posterior"),
                                   views.series_view("Posterior", *posterior),
                                   views.state_view("Image status", "topo/status")), columns=[3, 2]),
            views.tab("Map over time", views.map_view("Graph: odometry edges, loop closures (green)", "world", bounds),
                      rrb.Vertical(views.series_view("Locations", "metrics/locations"),
                                   views.log_view("Loop closures and relaxations", "topo/log")), columns=[3, 2]),
            views.tab("Data", views.data_view()),
            views.tab("Log", views.log_view("Log", "log", "topo/log")),
        )
