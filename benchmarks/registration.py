"""Image registration: ours (iFMI) against imreg_dft and an OpenCV phaseCorrelate + warpPolar pipeline.

All three register the same pairs in one run, single-threaded (OMP/OpenBLAS/MKL threads set to 1
before NumPy loads, ``cv2.setNumThreads(1)``; ours and the OpenCV recipe call no threaded code,
imreg_dft runs NumPy's FFT and SciPy's ``ndimage``). Pairs follow the convention of
:func:`slamreplay.algorithms.ifmi.register` exactly::

    A = cv2.getRotationMatrix2D(((N - 1) / 2, (N - 1) / 2), angle, scale); A[:, 2] += (dx, dy)
    moving = cv2.warpAffine(reference_extended, A, (N, N))

with angle uniform in [-180, 180), scale log-uniform in [0.8, 1.25] and each shift uniform in
+-20 % of N. ``reference`` is an N x N crop of a larger source and ``moving`` is rendered from
the source around it (mirrored beyond the source's edge), so the content that rotates into
the corners is the scene's own, as with a real camera.

Sources: ``procedural`` (the seeded ``sim-seabed`` texture, 2048 x 2048) and ``skerki`` (the
real underwater frames of ``skerki-underwater-group29``, 576 x 384; enlarged 1.5x for the 512
pairs, which do not fit otherwise). Skerki is skipped when the data folder is absent.

Each method's answer is turned into the 2x3 affine it claims (imreg_dft's by applying its own
``transform_img`` to coordinate ramps, so its result is read by its own definition, outside
the timed call) and compared with the truth: angle, scale and centre-shift errors, and the
RMS displacement over the reference's pixel grid; a pair succeeds when that RMS is below
``--success-px``. Times are the median over pairs of one call each (ours: ``register`` on two
raw images; "ours seq": one image's ``prepare`` plus ``register_prepared``, the sequential mode),
wall clock and process CPU time (the steadier figure when other work shares the machine). The
order of the methods rotates from pair to pair (``--fixed-order``: always ours first), so that
none of them always pays for the caches the previous method flushed.

``--nees`` runs the calibration study of the paper's translation covariance (eq. 10) instead: the
NEES of the translation error against it on pairs perturbed by sensor noise and blur (paper
against calibrated: benchmarks/ifmi_calibration.py).

Run: ``.venv/bin/python benchmarks/registration.py [--pairs 40] [--sizes 256 512] [--data ../shared/data] [--nees]
[--translation-band 1] [--json PATH]``.
Peer: ``pip install imreg_dft`` (skipped with a note when missing).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from bench_io import write_json  # noqa: E402

from slamreplay.algorithms.ifmi import IfmiConfig, Status, prepare, register, register_prepared  # noqa: E402
from slamreplay.recorder.sim.seabed import procedural_texture  # noqa: E402

cv2.setNumThreads(1)

try:
    import imreg_dft  # type: ignore[import-untyped]
except ImportError:  # the peer is optional
    imreg_dft = None


@dataclass(frozen=True, slots=True)
class Pair:
    """A reference crop, the moving image and the true affine (module convention)."""

    reference: np.ndarray
    moving: np.ndarray
    truth: np.ndarray  # (2, 3)


def true_affine(n: int, angle: float, scale: float, dx: float, dy: float) -> np.ndarray:
    """The convention of ``register``: rotation/scale about the centre, then the shift."""
    a = cv2.getRotationMatrix2D(((n - 1) / 2.0, (n - 1) / 2.0), angle, scale)
    a[:, 2] += (dx, dy)
    return np.asarray(a)


def make_pairs(sources: list[np.ndarray], n: int, count: int, rng: np.random.Generator) -> list[Pair]:
    """``count`` random similarity pairs of size ``n`` from crops of ``sources`` (cycled)."""
    pairs = []
    for k in range(count):
        src = sources[k % len(sources)]
        angle = float(rng.uniform(-180.0, 180.0))
        scale = math.exp(rng.uniform(math.log(0.8), math.log(1.25)))
        dx, dy = (rng.uniform(-0.2, 0.2, 2) * n).tolist()
        y = int(rng.integers(0, src.shape[0] - n + 1))
        x = int(rng.integers(0, src.shape[1] - n + 1))
        a = true_affine(n, angle, scale, dx, dy)
        a_src = a.copy()
        a_src[:, 2] -= a[:, :2] @ np.array([x, y], float)  # source pixel -> moving pixel
        moving = cv2.warpAffine(src, a_src, (n, n), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        pairs.append(Pair(src[y:y + n, x:x + n].copy(), moving, a))
    return pairs


def decompose(a: np.ndarray, n: int) -> tuple[float, float, float, float]:
    """(angle deg, scale, dx, dy) of a 2x3 similarity in the convention of ``register``."""
    angle = math.degrees(math.atan2(a[0, 1], a[0, 0]))
    scale = math.hypot(a[0, 0], a[0, 1])
    base = true_affine(n, angle, scale, 0.0, 0.0)
    return angle, scale, float(a[0, 2] - base[0, 2]), float(a[1, 2] - base[1, 2])


def errors(est: np.ndarray, truth: np.ndarray, n: int) -> tuple[float, float, float, float]:
    """(|angle error| deg, |scale error| %, centre-shift error px, grid RMS displacement px)."""
    ae, se, xe, ye = decompose(est, n)
    at, st, xt, yt = decompose(truth, n)
    g = np.mgrid[0:n:8, 0:n:8].reshape(2, -1)[::-1].astype(float)
    g = np.vstack([g, np.ones(g.shape[1])])
    rms = float(np.sqrt(np.mean(np.sum((est @ g - truth @ g) ** 2, axis=0))))
    return abs((ae - at + 180.0) % 360.0 - 180.0), 100.0 * abs(se / st - 1.0), math.hypot(xe - xt, ye - yt), rms


# ---------------------------------------------------------------------------------------------------------------
# Peer 1: the OpenCV recipe (what a user would write from the docs and the usual FMI tutorials).


class OpenCvLogPolar:
    """Hann window, |DFT| with the Reddy-Chatterji high-pass, ``warpPolar`` (log), ``phaseCorrelate`` for the
    rotation/scale; then the reference re-rotated/scaled at theta and theta + 180 and ``phaseCorrelate`` (with
    the window) against the moving image, the higher response winning. Maps and window cached per size."""

    def __init__(self, shape: tuple[int, int]) -> None:
        h, w = shape
        self.shape = shape
        self.window = cv2.createHanningWindow((w, h), cv2.CV_32F)
        fy = np.fft.fftshift(np.fft.fftfreq(h))
        fx = np.fft.fftshift(np.fft.fftfreq(w))
        x = np.cos(np.pi * fy)[:, None] * np.cos(np.pi * fx)[None, :]
        self.highpass = ((1.0 - x) * (2.0 - x)).astype(np.float32)
        self.max_radius = min(h, w) / 2.0
        self.polar = (w, h)  # (log-radius bins, angle bins over 360 degrees)

    def _log_polar(self, img: np.ndarray) -> np.ndarray:
        h, w = self.shape
        f = cv2.dft(cv2.multiply(img, self.window), flags=cv2.DFT_COMPLEX_OUTPUT)
        mag = np.fft.fftshift(cv2.magnitude(f[..., 0], f[..., 1])) * self.highpass
        return cv2.warpPolar(mag, self.polar, (w // 2, h // 2), self.max_radius,
                             cv2.WARP_POLAR_LOG | cv2.INTER_LINEAR)

    def __call__(self, reference: np.ndarray, moving: np.ndarray) -> np.ndarray:
        h, w = self.shape
        a, b = reference.astype(np.float32), moving.astype(np.float32)
        (sx, sy), _ = cv2.phaseCorrelate(self._log_polar(a), self._log_polar(b))
        angle = -sy * 360.0 / h
        scale = math.exp(-sx * math.log(self.max_radius) / w)
        best: tuple[float, np.ndarray] | None = None
        for theta in (angle, angle + 180.0):
            m = cv2.getRotationMatrix2D(((w - 1) / 2.0, (h - 1) / 2.0), theta, scale)
            warped = cv2.warpAffine(a, m, (w, h), flags=cv2.INTER_LINEAR)
            (tx, ty), response = cv2.phaseCorrelate(warped, b, self.window)
            if best is None or response > best[0]:
                m[:, 2] += (tx, ty)
                best = (response, m)
        assert best is not None
        return best[1]


# ---------------------------------------------------------------------------------------------------------------
# Peer 2: imreg_dft (matejak/imreg_dft), the reference Python FMI.


def imreg_dft_call(reference: np.ndarray, moving: np.ndarray) -> dict[str, Any]:
    """``imreg_dft.similarity(reference, moving)``: parameters that take ``moving`` onto ``reference``."""
    return imreg_dft.similarity(reference.astype(np.float64), moving.astype(np.float64))  # type: ignore[no-any-return]


def imreg_dft_affine(result: dict[str, Any], n: int) -> np.ndarray:
    """The affine imreg_dft's answer means, read by its own ``transform_img`` (untimed).

    ``transform_img(moving, result)`` should equal ``reference``; applied to images holding each
    pixel's x and y coordinate (bilinear, so exact for ramps) it tells, for every reference pixel,
    the moving pixel it takes: that map is ``A`` of the convention.
    """
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    kw = {"scale": result["scale"], "angle": result["angle"], "tvec": result["tvec"], "order": 1}
    mx = imreg_dft.transform_img(xx, bgval=-1e6, **kw)
    my = imreg_dft.transform_img(yy, bgval=-1e6, **kw)
    inside = (mx > -1.0) & (my > -1.0)
    inside[:2, :] = inside[-2:, :] = False
    inside[:, :2] = inside[:, -2:] = False
    src = np.column_stack([xx[inside], yy[inside], np.ones(int(inside.sum()))])
    sol, *_ = np.linalg.lstsq(src, np.column_stack([mx[inside], my[inside]]), rcond=None)
    return np.asarray(sol.T)


# ---------------------------------------------------------------------------------------------------------------


@dataclass
class Method:
    name: str
    call: Callable[[np.ndarray, np.ndarray], Any]
    to_affine: Callable[[Any], np.ndarray]
    accepted: Callable[[Any], bool] | None = None
    setup: Callable[[np.ndarray, np.ndarray], None] | None = None  # untimed, before each timed call


def load_sources(data: Path, n: int) -> dict[str, list[np.ndarray]]:
    """The textured sources for pairs of size ``n`` (module docstring)."""
    out = {"procedural": [procedural_texture(2048, 2048, np.random.default_rng(7))]}
    frames = sorted((data / "skerki-underwater-group29").glob("*.png"))
    if frames:
        imgs = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in frames]
        if n > min(imgs[0].shape):
            f = 1.5 * n / 512
            imgs = [cv2.resize(i, None, fx=f, fy=f, interpolation=cv2.INTER_CUBIC) for i in imgs]
        out["skerki"] = imgs
    return out


def run(pairs: list[Pair], methods: list[Method], n: int, success_px: float, rotate: bool = True
        ) -> dict[str, dict[str, float]]:
    """Every method on every pair, interleaved so that machine load hits all alike.

    With ``rotate`` the order of the methods turns by one from pair to pair: the method that runs
    first after the previous pair's last one (imreg_dft and its untimed ``transform_img``, which
    flush the caches) pays for refilling them, and in a fixed order that was always ``ours``.
    """
    for m in methods:  # warm-up: caches, imports, first-call costs
        for p in pairs[:2]:
            if m.setup is not None:
                m.setup(p.reference, p.moving)
            m.call(p.reference, p.moving)
    times: dict[str, list[float]] = {m.name: [] for m in methods}
    cpu: dict[str, list[float]] = {m.name: [] for m in methods}
    errs: dict[str, list[tuple[float, float, float, float]]] = {m.name: [] for m in methods}
    acc: dict[str, list[bool]] = {m.name: [] for m in methods}
    for k, p in enumerate(pairs):
        turn = k % len(methods) if rotate else 0
        for m in methods[turn:] + methods[:turn]:
            if m.setup is not None:
                m.setup(p.reference, p.moving)
            c, t = time.process_time(), time.perf_counter()
            out = m.call(p.reference, p.moving)
            times[m.name].append(time.perf_counter() - t)
            cpu[m.name].append(time.process_time() - c)
            errs[m.name].append(errors(m.to_affine(out), p.truth, n))
            if m.accepted is not None:
                acc[m.name].append(m.accepted(out))
    table = {}
    for m in methods:
        e = np.array(errs[m.name])
        row = {"ms": 1e3 * float(np.median(times[m.name])), "cpu_ms": 1e3 * float(np.median(cpu[m.name])),
               "success": 100.0 * float(np.mean(e[:, 3] < success_px)),
               "angle_deg": float(np.median(e[:, 0])), "scale_pct": float(np.median(e[:, 1])),
               "shift_px": float(np.median(e[:, 2])), "grid_px": float(np.median(e[:, 3]))}
        if acc[m.name]:
            row["accepted"] = 100.0 * float(np.mean(acc[m.name]))
        table[m.name] = row
    return table


# ---------------------------------------------------------------------------------------------------------------
# Calibration of the translation covariance (eq. 10): NEES on perturbed pairs.

CHI2_2_95 = 5.991  # 95 % quantile of chi-square with 2 degrees of freedom
PERTURBATIONS: dict[str, tuple[float, float]] = {  # name: (Gaussian noise sigma on both images, blur sigma on moving)
    "clean": (0.0, 0.0), "noise 3": (3.0, 0.0), "noise 6": (6.0, 0.0), "blur 1": (0.0, 1.0),
    "blur 1 + noise 3": (3.0, 1.0),
}


def perturb(pair: Pair, noise: float, blur: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The pair with sensor noise on both images and a blur (focus, altitude) on the moving one."""
    ref, mov = pair.reference.astype(np.float32), pair.moving.astype(np.float32)
    if blur > 0:
        mov = cv2.GaussianBlur(mov, (0, 0), blur)
    if noise > 0:
        ref = ref + rng.normal(0.0, noise, ref.shape).astype(np.float32)
        mov = mov + rng.normal(0.0, noise, mov.shape).astype(np.float32)
    return ref, mov


def nees_table(sources: dict[str, list[np.ndarray]], n: int, count: int, seed: int) -> None:
    """NEES ``e^T C^-1 e`` of the translation error ``e`` against the eq. (10) covariance ``C``, per condition.

    A calibrated covariance gives a mean NEES of 2 and 95 % of the pairs below the chi2(2) bound;
    a mean below 2 means the covariance is too large (conservative) by about ``2 / mean``.
    """
    print(f"\nNEES of the translation (accepted pairs; chi2(2) 95 % bound {CHI2_2_95}), {n} x {n}, {count} pairs each")
    print(f"{'condition':<18} {'source':<11} {'accepted':>8} {'mean NEES':>10} {'median':>8} {'<= bound':>8} "
          f"{'err RMS px':>10} {'sigma px':>9} {'C too big':>9}")
    for name, (noise, blur) in PERTURBATIONS.items():
        for source, images in sources.items():
            rng = np.random.default_rng(seed)
            pairs = make_pairs(images, n, count, rng)
            nees, err, sigma, accepted = [], [], [], 0
            for p in pairs:
                ref, mov = perturb(p, noise, blur, rng)
                r = register(ref, mov, IfmiConfig(covariance="paper"))
                if r.status is not Status.OK:
                    continue
                accepted += 1
                _, _, dx, dy = decompose(p.truth, n)
                e = np.array([r.shift_px[0] - dx, r.shift_px[1] - dy])
                c = r.covariance[:2, :2]
                nees.append(float(e @ np.linalg.solve(c, e)))
                err.append(float(e @ e))
                sigma.append(math.sqrt(0.5 * float(np.trace(c))))
            if not nees:
                print(f"{name:<18} {source:<11} {accepted:>4}/{count:<3} (none accepted)")
                continue
            v = np.array(nees)
            print(f"{name:<18} {source:<11} {accepted:>4}/{count:<3} {v.mean():10.4f} {np.median(v):8.4f} "
                  f"{100 * np.mean(v <= CHI2_2_95):7.0f}% {math.sqrt(np.mean(err)):10.3f} {np.median(sigma):9.3f} "
                  f"{2.0 / v.mean():8.0f}x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=40, help="pairs per source and size")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--data", type=Path, default=Path(os.environ.get("SLAMREPLAY_DATA", "../shared/data")))
    parser.add_argument("--success-px", type=float, default=2.0, help="grid RMS error below which a pair succeeds")
    parser.add_argument("--no-imreg-dft", action="store_true", help="skip the slow peer")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--nees", action="store_true", help="only the covariance calibration (NEES) study")
    parser.add_argument("--fixed-order", action="store_true",
                        help="run the methods in the same order on every pair (ours always first) instead of rotating")
    parser.add_argument("--translation-band", type=int, default=IfmiConfig().translation_band,
                        help="ours: IfmiConfig.translation_band (1: the paper's full band; default %(default)s)")
    parser.add_argument("--json", type=Path, help="write every row here")
    args = parser.parse_args()
    try:
        IfmiConfig(translation_band=args.translation_band)
    except ValueError as e:
        parser.error(str(e))
    if args.nees:
        for n in args.sizes:
            nees_table(load_sources(args.data, n), n, args.pairs, args.seed)
        return
    if imreg_dft is None and not args.no_imreg_dft:
        print("note: imreg_dft skipped (pip install imreg_dft)")
    print(f"threads: 1 (cv2 {cv2.__version__}, numpy {np.__version__}); success = grid RMS < {args.success_px} px; "
          f"times = median per pair of wall (ms/pair) and process CPU time (cpu ms, steadier on a shared machine)")
    hdr = f"{'size':>5} {'source':<11} {'method':<13} {'ms/pair':>8} {'cpu ms':>7} {'success':>8} {'accepted':>8} " \
          f"{'angle deg':>10} {'scale %':>8} {'shift px':>9} {'grid px':>8}"
    rows: list[dict[str, Any]] = []
    for n in args.sizes:
        config = IfmiConfig(translation_band=args.translation_band)
        ocv = OpenCvLogPolar((n, n))
        held: list[Any] = [None]

        def hold(ref: np.ndarray, _mov: np.ndarray, cfg: IfmiConfig = config, h: list[Any] = held) -> None:
            h[0] = prepare(ref, cfg)  # the previous image's spectra, kept by the sequential mode

        def seq(_ref: np.ndarray, mov: np.ndarray, cfg: IfmiConfig = config, h: list[Any] = held) -> Any:
            return register_prepared(h[0], prepare(mov, cfg), cfg)

        methods = [
            Method("ours", lambda r, m, cfg=config: register(r, m, cfg), lambda out, n=n: out.matrix((n, n)),
                   lambda out: out.status is Status.OK),
            Method("ours seq", seq, lambda out, n=n: out.matrix((n, n)), lambda out: out.status is Status.OK, hold),
            Method("opencv", ocv, lambda out: out),
        ]
        if imreg_dft is not None and not args.no_imreg_dft:
            methods.append(Method("imreg_dft", imreg_dft_call, lambda out, n=n: imreg_dft_affine(out, n)))
        for source, images in load_sources(args.data, n).items():
            rng = np.random.default_rng(args.seed)
            pairs = make_pairs(images, n, args.pairs, rng)
            table = run(pairs, methods, n, args.success_px, rotate=not args.fixed_order)
            rows += [{"size": n, "source": source, "method": name, **row} for name, row in table.items()]
            print()
            print(hdr)
            for name, row in table.items():
                acc = f"{row['accepted']:7.0f}%" if "accepted" in row else f"{'-':>8}"
                print(f"{n:>5} {source:<11} {name:<13} {row['ms']:8.2f} {row['cpu_ms']:7.2f} "
                      f"{row['success']:7.0f}% {acc} "
                      f"{row['angle_deg']:10.4f} {row['scale_pct']:8.4f} {row['shift_px']:9.4f} {row['grid_px']:8.4f}")
            for col, label in (("ms", "wall"), ("cpu_ms", "cpu")):
                ours = table["ours"][col]
                ratios = [f"ours/{k} = {ours / v[col]:.3f} ({v[col] / ours:.1f}x faster)"
                          for k, v in table.items() if not k.startswith("ours")]
                print(f"{'':>5} {'':<11} {label} time ratios: " + "; ".join(ratios))
    if args.json:
        write_json(args.json, {"pairs": args.pairs, "translation_band": args.translation_band, "rows": rows})


if __name__ == "__main__":
    main()
