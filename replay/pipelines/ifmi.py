"""Pipeline ``ifmi``: iFMI photo-mapping (Pfingsthorn, Birk et al., ICRA 2010) over ``/camera/image``.

Per image: a node; the registration of the previous image onto it (sequential mode: each
image's spectra are computed once); loop-closure candidates, the earlier nodes whose current
estimate lies within ``loop_radius`` image footprints, registered and accepted by PNR
(section III-B) and, beyond the paper, only when consistent with the current estimate
(``loop_gate_deg``, ``loop_gate_footprints``: the mud of the Skerki frames gives PNR-accepted
matches of the lamp's pattern at 90 or 180 degrees). A rejected consecutive registration
becomes an almost free edge along the previous motion (a survey flies steadily), so the graph
stays connected and the loops decide. Edge information is the inverse of the registration
covariance (eq. 10; ``covariance=calibrated`` for the calibrated form of docs/ifmi.md), propagated
into the node frame. At the end the scales (altitude) are solved in the log, the planar graph
is optimized with the pose-graph back end, and the squared Mahalanobis sum over all edges is
reported before and after, with mosaics from both sets of poses.

Illumination, with no per-dataset setting: each image goes through a homomorphic high-pass
(the lamp's light multiplies the scene). That alone leaves the frames' fixed pattern (the
Skerki camera's vertical stripes, the rim of the hot spot) to lock the full-band POMF at
(0, 0); the registration reads the PNR in the finest band where the Dirac is clear
(:func:`slamreplay.algorithms.ifmi.spectral.band_peak`), below those frequencies. Subtracting the
sequence's mean image, as the data's README suggests, put a ghost of every frame into every
frame and lowered the accepted consecutive Skerki pairs from 48 to 45 of 56 (the mean of all
frames) or 36 (a running mean).

Units: metres when the recording states ``metres_per_pixel`` (sim-seabed) or the config does;
otherwise pixels of the first image. Pixel metrics divide by it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import rerun.blueprint as rrb

from slamreplay.algorithms.common import se2
from slamreplay.algorithms.common.posegraph import OptimizerConfig, PoseGraph, chi2, optimize
from slamreplay.algorithms.common.posegraph_analysis import marginal_covariances
from slamreplay.algorithms.ifmi import IfmiConfig, Prepared, Registration, Status, prepare, register_prepared
from slamreplay.algorithms.ifmi.mapping import (
    edge_from_registration,
    flatten_illumination,
    gated_log_scales,
    mosaic_consistency,
    render_mosaic,
    solve_log_scales,
)
from slamreplay.algorithms.ifmi.plan import MIN_SIZE
from slamreplay.algorithms.observe import CovarianceEllipses, Image, LineStrips, Points, Scalar, Segments, State, Text
from slamreplay.recorder.messages import TOPIC_CAMERA_IMAGE, TOPIC_GROUND_TRUTH_POSE, CameraImage, GroundTruthPose
from slamreplay.replay.engine import views
from slamreplay.replay.engine.pipeline import Pipeline, ReplayContext
from slamreplay.replay.engine.reader import Envelope
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.metric_registry import specs

SCALE_GATE = 10.83  # chi2 (1 dof) 99.9 % quantile: an edge's scale this far off is left out (calibrated only)
WEAK_SIGMA = 1e3  # a rejected consecutive registration keeps the graph connected with a nearly free edge


@dataclass(frozen=True, slots=True)
class _Edge:
    """A registration of image i (reference) onto image j, and whether it enters the graph as a measurement."""

    i: int
    j: int
    reg: Registration
    ok: bool  # PNR accepted (and, for a loop closure, consistent with the estimate)
    prior: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rejected consecutive pair: the assumed motion


@dataclass(frozen=True, slots=True)
class IfmiPipelineConfig:
    """Parameters of the ``ifmi`` pipeline."""

    min_pnr: float = field(default=0.2, metadata={"help": "PNR (eq. 13) a registration needs to be accepted"})
    loop_radius: float = field(default=0.8, metadata={"help": "loop candidates: earlier nodes within this many image "
                                                              "footprints of the current estimate"})
    max_candidates: int = field(default=4, metadata={"help": "nearest earlier nodes registered per image"})
    min_gap: int = field(default=3, metadata={"help": "loop candidates are at least this many images back"})
    metres_per_pixel: float = field(default=0.0, metadata={"help": "metres per image pixel; 0: the recording's "
                                                                   "(sim-seabed states it), else 1 (pixel units)"})
    mosaic_max_px: int = field(default=1600, metadata={"help": "the logged mosaics' longer side, at most (pixels)"})
    mosaic_every: int = field(default=10, metadata={"help": "draw the growing (dead-reckoned) mosaic every this many "
                                                            "images; 0: only at the end"})
    loop_gate_deg: float = field(default=30.0, metadata={"help": "a loop closure further than this from the "
                                                                 "estimated relative heading is rejected"})
    loop_gate_footprints: float = field(default=0.5, metadata={"help": "... or further than this many footprints "
                                                                       "from the estimated offset"})
    # The paper's stays the pipeline's default by measurement on the real Skerki sequence: calibrated edges leave out 14
    # of 23 loop closures there and its mosaic agrees less with itself (NCC 0.190 against 0.223), although they give
    # the better sim-seabed graphs (docs/ifmi.md, "Effect on the pose graph").
    covariance: str = field(default="paper", metadata={"help": (
        "registration covariance: paper (eq. 10, the POMF peak's width) or calibrated (docs/ifmi.md)")})
    # 1 goes with the paper's covariance: eq. (10) of band 2 is 4x wider, and sim-seabed's ATE grew 0.27 -> 0.35 px; 2
    # with covariance=calibrated gave the best sim-seabed graphs (docs/ifmi.md, "The translation's band").
    translation_band: int = field(default=1, metadata={"help": (
        "finest band the translation peak is read in: 1 all frequencies (the paper), 2 the lower half (fewer "
        "interpolation errors; best with covariance=calibrated)")})

    def __post_init__(self) -> None:
        self.registration()  # min_pnr, covariance and translation_band: IfmiConfig's checks and messages
        if not self.loop_radius >= 0:
            raise ValueError(f"loop_radius must be >= 0, got {self.loop_radius}")
        if self.max_candidates < 0 or self.min_gap < 2:
            raise ValueError("max_candidates must be >= 0 and min_gap >= 2")
        if self.mosaic_every < 0:
            raise ValueError(f"mosaic_every must be >= 0, got {self.mosaic_every}")
        if not self.metres_per_pixel >= 0 or self.mosaic_max_px < 64:
            raise ValueError("metres_per_pixel must be >= 0 and mosaic_max_px >= 64")
        if not (self.loop_gate_deg > 0 and self.loop_gate_footprints > 0):
            raise ValueError("loop_gate_deg and loop_gate_footprints must be > 0")

    def registration(self) -> IfmiConfig:
        """The registration's configuration these keys make."""
        return IfmiConfig(min_pnr=self.min_pnr, covariance=self.covariance, translation_band=self.translation_band)


class IfmiPipeline(Pipeline):
    name = "ifmi"
    summary = "iFMI photo-mapping: spectral registration with POMF covariance and PNR, pose graph, mosaics"
    required_topics = (TOPIC_CAMERA_IMAGE,)
    optional_topics = (TOPIC_GROUND_TRUTH_POSE,)
    start_topic = TOPIC_CAMERA_IMAGE
    Config = IfmiPipelineConfig
    # ``--preset paper``: the registration covariance of the paper (eq. 10), its translation peak read in the full band
    # (both the pipeline's defaults); the other extras (band-limited PNR, loop gates, illumination flattening) have no
    # paper-exact switch.
    presets: ClassVar[dict[str, dict[str, Any]]] = {"paper": {"covariance": "paper", "translation_band": 1}}
    preset_notes: ClassVar[dict[str, str]] = {
        "covariance": "the paper reads the edge covariance off the POMF peak's neighbourhood (eq. 10): the peak's "
                      "width, 10-200x the error variance on known warps; the extra divides the translation's by "
                      "PNR sqrt(H W) and takes the rotation's from the phase residuals "
                      "(algorithms/ifmi/covariance.py, docs/ifmi.md)",
        "translation_band": "the paper reads the translation peak in the POMF of all frequencies; the extra (2) leaves "
                            "out the upper half, where the bilinear warps garble the phase: on known warps 1.1-3.4x "
                            "smaller shift errors, and the Skerki frames' translation NEES 4.2-4.3 -> 1.2-1.5 with the "
                            "calibrated covariance (docs/ifmi.md, \"The translation's band\")",
    }
    trajectory_metrics = False  # its poses are in mosaic pixels: ate_rmse_px
    metrics = specs("images", "registrations", "registrations_accepted", "pnr_median", "loop_closures",
                    "chi2_initial", "chi2_final", "chi2_per_dof", "mosaic_ncc", "edges_rejected", "ate_rmse_px_initial",
                    "ate_rmse_px", "rotation_error_deg_median", "translation_error_px_median")

    summary_skip = (*views.SUMMARY_SKIP, "graph/before", "graph/estimate")

    @classmethod
    def blueprint(cls, bounds: views.Bounds | None = None) -> rrb.Blueprint:
        pnr = ("ifmi/pnr", "ifmi/pnr_threshold")
        return views.layout(
            views.summary_tab(bounds, pnr, "PNR of consecutive pairs (eq. 13) and the acceptance threshold",
                              side=views.image_view("Mosaic at the optimized poses", "/ifmi/mosaic/after")),
            views.tab("Registration",
                      rrb.Vertical(views.image_view("Image pair: previous | current", "/camera/pair"),
                                   rrb.Horizontal(views.image_view("POMF rotation-scale (log-polar, log scale), peak",
                                                                   "/ifmi/pomf/rotation_scale"),
                                                  views.image_view("POMF translation (log scale), peak",
                                                                   "/ifmi/pomf/translation"))),
                      rrb.Vertical(views.series_view("PNR and threshold", *pnr),
                                   views.state_view("Registrations: consecutive, loop candidates",
                                                    "ifmi/state/consecutive", "ifmi/state/loop_candidates"),
                                   views.log_view("Decisions", "ifmi/decision")), columns=[3, 2]),
            views.tab("Pose graph",
                      views.map_view("Before optimization: accepted (green), rejected (red), 2-sigma", "world", bounds,
                                     exclude=["graph/after/**", "graph/estimate/**"]),
                      views.map_view("After optimization", "world", bounds,
                                     exclude=["graph/before/**", "graph/estimate/**"])),
            views.tab("Mosaic",
                      views.image_view("Growing mosaic (dead-reckoned poses)", "/ifmi/mosaic/growing"),
                      views.image_view("Before optimization", "/ifmi/mosaic/before"),
                      views.image_view("After optimization", "/ifmi/mosaic/after")),
            views.tab("Log", views.log_view("Log", "log", "ifmi/decision")),
        )

    def __init__(self, config: IfmiPipelineConfig, ctx: ReplayContext) -> None:
        super().__init__(config, ctx)
        self.reg_config = config.registration()
        self.mpp = config.metres_per_pixel or _recorded_mpp(ctx) or 1.0
        self.start = ctx.T_world_start if ctx.T_world_start is not None else np.zeros(3)
        self.images: list[np.ndarray] = []
        self.prepared: list[Prepared] = []
        self.stamps: list[int] = []
        self.poses: list[np.ndarray] = []  # current estimate (dead reckoning through registrations)
        self.log_scale: list[float] = []
        self.edges: list[_Edge] = []
        self.motion = np.zeros(3)  # the last accepted consecutive motion (constant-velocity prior)
        self.pnrs: list[float] = []
        self.tried = 0
        self.t_gt: list[int] = []
        self.gt: list[np.ndarray] = []

    def step(self, env: Envelope) -> None:
        msg = env.msg
        if isinstance(msg, GroundTruthPose):
            self.t_gt.append(env.log_time_ns)
            self.gt.append(msg.xy_yaw)
            return
        if not isinstance(msg, CameraImage):
            return
        obs = self.ctx.observer
        k = len(self.images)
        gray = msg.pixels if msg.pixels.ndim == 2 else msg.pixels.mean(axis=2).astype(np.uint8)
        if min(gray.shape) < MIN_SIZE:
            raise ReplayError(f"image {k} at {env.log_time_ns} ns is {gray.shape[1]}x{gray.shape[0]} pixels; iFMI "
                              f"needs at least {MIN_SIZE}x{MIN_SIZE} (its log-polar spectra): record larger images")
        if k and gray.shape != self.images[0].shape:
            self.ctx.log(f"image {k} is {gray.shape} but the first was {self.images[0].shape}: skipped")
            return
        self.images.append(gray)
        self.stamps.append(env.log_time_ns)
        self.prepared.append(prepare(flatten_illumination(gray), self.reg_config, "image"))
        obs.log("camera/image", Image(gray))
        obs.log("ifmi/pnr_threshold", Scalar(self.config.min_pnr))
        if k:
            obs.log("camera/pair", Image(np.hstack([self.images[k - 1], gray])))
        if k == 0:
            self.poses.append(np.asarray(self.start, float))
            self.log_scale.append(0.0)
            return
        reg = register_prepared(self.prepared[k - 1], self.prepared[k], self.reg_config, obs)
        if reg.status is Status.OK:
            z, _ = edge_from_registration(reg, self.mpp * math.exp(-(self.log_scale[-1] + math.log(reg.scale))))
            self._count(reg, k - 1, k, True)
            self.motion = z
            self.log_scale.append(self.log_scale[-1] + math.log(reg.scale))
        else:
            # Keep moving as before (a survey flies steadily); the edge is almost free, loops decide.
            z = self.motion
            self._count(reg, k - 1, k, False, (float(z[0]), float(z[1]), float(z[2])))
            self.log_scale.append(self.log_scale[-1])
        self.poses.append(se2.compose(self.poses[-1], z))
        self._loop_candidates(k)
        obs.log("world/graph/estimate/nodes", Points(np.array(self.poses)[:, :2], radius=self._radius()))
        every = self.config.mosaic_every
        if every and (k + 1) % every == 0:
            res = self.mpp * np.exp(-np.asarray(self.log_scale))
            obs.log("ifmi/mosaic/growing", Image(render_mosaic(self.images, np.array(self.poses), res,
                                                               min(512, self.config.mosaic_max_px))))

    def _count(self, reg: Registration, i: int, j: int, ok: bool, prior: tuple[float, float, float] | None = None,
               why: str = "") -> None:
        self.tried += 1
        self.pnrs.append(reg.pnr)
        if ok or prior is not None:
            self.edges.append(_Edge(i, j, reg, ok, prior or (0.0, 0.0, 0.0)))
        why = why or reg.status.value
        if j == i + 1:
            self.ctx.observer.log("ifmi/state/consecutive", State("accepted" if ok else "rejected"))
        self.ctx.observer.log("ifmi/decision", Text(f"{i}->{j}: PNR {reg.pnr:.3f} (band {reg.band}) "
                                                    f"{'accepted' if ok else 'rejected'} ({why}), angle "
                                                    f"{reg.angle_deg:.2f} deg, scale {reg.scale:.4f}, shift "
                                                    f"{reg.shift_px[0]:.2f}, {reg.shift_px[1]:.2f} px",
                                                    "INFO" if ok else "WARN"))

    def _footprint(self) -> float:
        h, w = self.images[0].shape
        return float(self.mpp * min(h, w))

    def _radius(self) -> float:
        return 0.02 * self._footprint()

    def _loop_candidates(self, k: int) -> None:
        if self.config.max_candidates == 0 or k < self.config.min_gap:
            return
        p = np.array(self.poses[: k - self.config.min_gap + 1])
        d = np.hypot(*(p[:, :2] - self.poses[k][:2]).T)
        near = np.flatnonzero(d <= self.config.loop_radius * self._footprint())
        closed = False
        for i in near[np.argsort(d[near], kind="stable")][: self.config.max_candidates]:
            reg = register_prepared(self.prepared[int(i)], self.prepared[k], self.reg_config)
            ok, why = reg.status is Status.OK, ""
            if ok:
                # Section III-B accepts by PNR alone; low-texture frames (Skerki) also give PNR-accepted
                # matches of the lamp's pattern at 90 or 180 degrees, which no loop can be: a gate on the
                # current estimate (loose: it has drifted) keeps them out of the graph.
                z, _ = edge_from_registration(reg, self.mpp * math.exp(-self.log_scale[k]))
                dz = z - se2.between(self.poses[int(i)], self.poses[k])
                off = math.hypot(dz[0], dz[1]) / self._footprint()
                turn = abs(math.degrees(float(se2.wrap_angle(dz[2]))))
                if turn > self.config.loop_gate_deg or off > self.config.loop_gate_footprints:
                    ok, why = False, f"inconsistent with the estimate: {turn:.0f} deg, {off:.2f} footprints off"
            self._count(reg, int(i), k, ok, why=why)
            closed = closed or ok
        if len(near):
            self.ctx.observer.log("ifmi/state/loop_candidates", State("loop accepted" if closed else "all rejected"))

    def _graph(self) -> tuple[PoseGraph, np.ndarray]:
        """The planar graph at the dead-reckoned poses, and each node's metres per pixel."""
        n = len(self.images)
        ii = np.array([e.i for e in self.edges], np.int64)
        jj = np.array([e.j for e in self.edges], np.int64)
        ratio = np.array([math.log(e.reg.scale) if e.ok else 0.0 for e in self.edges])
        var = np.array([e.reg.scale_var / e.reg.scale**2 if e.ok else 1e6 for e in self.edges])
        if self.config.covariance == "calibrated":  # variances to trust: gate the loop closures' scales
            log_s, kept = gated_log_scales(n, ii, jj, ratio, var, SCALE_GATE)
            if not kept.all():
                self.ctx.log(f"scale solve: {int((~kept).sum())} edge scales beyond the chi2(1) 99.9 % gate left "
                             "out: " + ", ".join(f"{a}->{b}" for a, b in zip(ii[~kept], jj[~kept], strict=True)))
        else:
            log_s = solve_log_scales(n, ii, jj, ratio, var)
        res = self.mpp * np.exp(-log_s)
        z, info = [], []
        for e in self.edges:
            if e.ok:
                zk, cov = edge_from_registration(e.reg, float(res[e.j]))
                info.append(np.linalg.inv(cov))
            else:
                zk = np.array(e.prior)
                info.append(np.diag([WEAK_SIGMA**-2, WEAK_SIGMA**-2, 1e-4]))
            z.append(zk)
        graph = PoseGraph(np.array(self.poses), ii, jj, np.array(z).reshape(-1, 3), np.array(info).reshape(-1, 3, 3))
        return graph, res

    def finish(self) -> dict[str, float]:
        obs = self.ctx.observer
        n = len(self.images)
        accepted = [e for e in self.edges if e.ok]
        metrics: dict[str, float] = {"images": float(n), "registrations": float(self.tried),
                                     "registrations_accepted": float(len(accepted)),
                                     "loop_closures": float(sum(1 for e in accepted if e.j != e.i + 1))}
        if self.pnrs:
            metrics["pnr_median"] = float(np.median(self.pnrs))
        if n < 2 or not self.edges:
            self.ctx.log("fewer than two images: no graph to optimize")
            return metrics
        graph, res = self._graph()
        if self.config.covariance == "calibrated":
            # Calibrated edges: the back end's robust defaults (DCS from a graduated phi, then a chi2(3) 99.9 %
            # gate) are in their units; with eq. (10)'s covariances they would never act, so the paper's keeps
            # plain DCS at phi = 1 as before.
            opt = OptimizerConfig(method="lm", max_iterations=50)
        else:
            opt = OptimizerConfig(method="lm", max_iterations=50, graduated=False, inlier_gate=None)
        result = optimize(graph, opt)
        after = graph.with_poses(result.poses)
        metrics["chi2_initial"], metrics["chi2_final"] = chi2(graph), chi2(after)
        dof = 3 * (int(result.inliers.sum()) - (n - 1))
        if dof > 0:
            metrics["chi2_per_dof"] = float(result.edge_chi2[result.inliers].sum()) / dof
        metrics["edges_rejected"] = float(result.edges_rejected)
        self.ctx.log(f"pose graph: {n} nodes, {graph.n_edges} edges; squared Mahalanobis sum "
                     f"{metrics['chi2_initial']:.6g} -> {metrics['chi2_final']:.6g} ({result.status.value}, "
                     f"{result.iterations} iterations)")
        for tag, g in (("before", graph), ("after", after)):
            self._draw_graph(tag, g)
            obs.log(f"ifmi/mosaic/{tag}", Image(render_mosaic(self.images, g.poses, res, self.config.mosaic_max_px)))
        ncc = mosaic_consistency(self.images, after.poses, res)
        if len(ncc):
            metrics["mosaic_ncc"] = float(ncc.mean())
        metrics.update(self._scores(graph.poses, after.poses, accepted, res))
        return metrics

    def _draw_graph(self, tag: str, g: PoseGraph) -> None:
        """Edges, 2-sigma ellipses and the paper's Fig. 6 conflicts (a vertex projected through an edge)."""
        obs = self.ctx.observer
        p = g.poses
        ok = np.array([e.ok for e in self.edges], dtype=bool)
        obs.log(f"world/graph/{tag}/edges/accepted", Segments(p[g.i[ok], :2], p[g.j[ok], :2]))
        obs.log(f"world/graph/{tag}/edges/rejected", Segments(p[g.i[~ok], :2], p[g.j[~ok], :2]))
        obs.log(f"world/graph/{tag}/nodes", Points(p[:, :2], radius=self._radius()))
        try:
            cov = marginal_covariances(g, np.arange(g.n_vertices))
            obs.log(f"world/graph/{tag}/covariance", CovarianceEllipses(p[:, :2], cov[:, :2, :2]))
        except ValueError as err:
            self.ctx.log(f"marginal covariances ({tag}): {err}")
        proj = se2.compose(p[g.i], g.measurements)
        off = np.hypot(*(proj[:, :2] - p[g.j, :2]).T)
        bad = off > 0.01 * self._footprint()
        obs.log(f"world/graph/{tag}/conflicts", Segments(proj[bad, :2], p[g.j[bad], :2]))
        obs.log(f"world/graph/{tag}/conflicts/projected", Points(proj[bad, :2], radius=self._radius()))
        obs.log(f"ifmi/conflicts_{tag}", Scalar(float(bad.sum())))

    def _scores(self, before: np.ndarray, after: np.ndarray, accepted: list[_Edge], res: np.ndarray
                ) -> dict[str, float]:
        if len(self.gt) < 2:
            return {}
        t_gt = np.asarray(self.t_gt, np.int64)
        t = np.asarray(self.stamps, np.int64)
        inside = (t >= t_gt[0]) & (t <= t_gt[-1])
        if inside.sum() < 2:
            return {}
        truth = se2.interpolate((t - t_gt[0]).astype(float), (t_gt - t_gt[0]).astype(float), np.array(self.gt))
        self.ctx.observer.log("world/trajectory/truth", LineStrips((truth[:, :2],)))
        ate0, _ = _aligned_rmse(before[inside], truth[inside])
        ate, scale = _aligned_rmse(after[inside], truth[inside])
        out = {"ate_rmse_px_initial": ate0 / self.mpp, "ate_rmse_px": ate / self.mpp}
        rot, trans = [], []
        for e in accepted:
            i, j = e.i, e.j
            if inside[i] and inside[j]:
                z, _ = edge_from_registration(e.reg, float(res[j]))
                true = se2.between(truth[i], truth[j])
                rot.append(abs(math.degrees(float(se2.wrap_angle(z[2] - true[2])))))
                trans.append(math.hypot(scale * z[0] - true[0], scale * z[1] - true[1]) / self.mpp)
        if rot:
            out["rotation_error_deg_median"] = float(np.median(rot))
            out["translation_error_px_median"] = float(np.median(trans))
        return out


def _recorded_mpp(ctx: ReplayContext) -> float | None:
    """``metres_per_pixel`` from the recording's generating parameters (sim-seabed), if stated."""
    meta = ctx.info.metadata.get("slamreplay.recording", {})
    try:
        value = json.loads(meta.get("parameters", "{}")).get("metres_per_pixel")
    except (json.JSONDecodeError, AttributeError):
        return None
    return float(value) if isinstance(value, (int, float)) and value > 0 else None


def _aligned_rmse(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Position RMSE after a least-squares similarity alignment (Umeyama), and its scale.

    Images fix no metric scale (the first image's altitude is unknown), so the estimate is scaled too.
    """
    p, q = est[:, :2], truth[:, :2]
    mp, mq = p.mean(0), q.mean(0)
    pc, qc = p - mp, q - mq
    u, s, vt = np.linalg.svd(qc.T @ pc / len(p))
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    var = float((pc**2).sum() / len(p))
    scale = float(np.trace(np.diag(s) @ d)) / var if var > 0 else 1.0
    aligned = scale * pc @ rot.T + mq
    return float(np.sqrt(np.mean(np.sum((aligned - q) ** 2, axis=1)))), scale
