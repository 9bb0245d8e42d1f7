"""Calibration of the iFMI registration covariance: NEES on known warps, paper (eq. 10) against calibrated.

Pairs follow the convention of docs/ifmi.md: ``A = cv2.getRotationMatrix2D(((N - 1) / 2, (N - 1) / 2),
angle, scale)``, ``A[:, 2] += (dx, dy)``, ``moving = cv2.warpAffine(reference, A, (N, N))``, with the
reference extended by its source (the moving image is rendered from the source around the crop, so
what turns into the corners is the scene's own, as with a camera). Angle uniform in [-180, 180),
scale log-uniform in [0.8, 1.25], shifts uniform in +-20 % of N (+-40 % for partial overlap).

Sources: ``procedural`` (the seeded ``sim-seabed`` texture, 2048 x 2048: the calibration's one
fitted constant, ``covariance.ROTATION_GAIN``, comes from it), and two held-out real ones, the
Skerki underwater frames ``skerki-underwater-group29`` and ``skerki-underwater-seq0658-0714``
(576 x 384; enlarged for N > 384), plus any folder of images given with ``--images`` (e.g. the
indoor ``rtabmap-loop-samples/images``, a different kind of scene: docs/ifmi.md). Conditions (noise
sigmas in grey levels of 8-bit images): ``clean``; ``noise 2/5/10`` (Gaussian sensor noise on both
images); ``illumination`` (the moving image times a gain in [0.7, 1.3] and a lamp-like linear ramp
of +-20 %, plus an offset, noise 3); ``overlap`` (shifts up to 40 %: 36-100 % overlap, noise 3);
``blur`` (Gaussian blur 1 px on the moving image, noise 3).

Per pair accepted by PNR (eq. 13): translation NEES ``e^T C^-1 e`` (2 dof) over (dx, dy) and
rotation NEES ``e_angle^2 / var_angle`` (1 dof; the scale's, 1 dof, in the JSON only), for both
``covariance`` settings on the same pair. A calibrated
covariance gives mean NEES 2 and 1 and 95 % of the pairs inside the chi2 bounds (5.991, 3.841);
``gm`` is the geometric mean of ``e^2 / C`` over the pairs, times the chi2 mean over its geometric
mean (1 when calibrated; robust to the heavy tails that move the mean).

Run: ``.venv/bin/python benchmarks/ifmi_calibration.py [--pairs 40] [--sizes 256] [--translation-band 1]
[--images DIR ...] [--json PATH]``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import math  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from bench_io import write_json  # noqa: E402

from slamreplay.algorithms.ifmi import IfmiConfig, Status, register  # noqa: E402
from slamreplay.algorithms.ifmi.covariance import LEVERS  # noqa: E402
from slamreplay.recorder.sim.seabed import procedural_texture  # noqa: E402

cv2.setNumThreads(1)

CHI2_95 = {1: 3.841, 2: 5.991}
GM_CHI2 = {1: 0.5 * math.exp(-0.5772157), 2: 2.0 * math.exp(-0.5772157)}  # geometric means of chi2_1, chi2_2
SKERKI = {"skerki-group29": "skerki-underwater-group29", "skerki-0658-0714": "skerki-underwater-seq0658-0714"}


@dataclass(frozen=True, slots=True)
class Condition:
    """A perturbation of the pair: sensor noise, illumination change, blur, the shift range (overlap)."""

    noise: float = 0.0
    illumination: bool = False
    blur: float = 0.0
    max_shift: float = 0.2


CONDITIONS = {
    "clean": Condition(), "noise 2": Condition(2.0), "noise 5": Condition(5.0), "noise 10": Condition(10.0),
    "illumination": Condition(3.0, illumination=True), "overlap": Condition(3.0, max_shift=0.4),
    "blur": Condition(3.0, blur=1.0),
}


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


def read_folder(folder: Path, n: int) -> list[np.ndarray]:
    """Every image of ``folder`` (grey), enlarged when ``n`` exceeds its smaller side (by ``1.5 n / 512``, as
    the Skerki frames for 512 px pairs); images smaller than 64 px are left out."""
    imgs = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted(folder.iterdir())
            if p.suffix.lower() in IMAGE_SUFFIXES]
    out = []
    for img in imgs:
        if img is None or min(img.shape) < 64:
            continue
        if n > min(img.shape):
            f = max(1.5 * n / 512, (n + 1) / min(img.shape))
            img = cv2.resize(img, None, fx=f, fy=f, interpolation=cv2.INTER_CUBIC)
        out.append(img)
    return out


def load_sources(data: Path, n: int, folders: tuple[Path, ...] = ()) -> dict[str, list[np.ndarray]]:
    """The images of every source: the procedural texture, the two Skerki sets under ``data`` (skipped when
    absent) and each of ``folders``, named ``parent/folder``."""
    out = {"procedural": [procedural_texture(2048, 2048, np.random.default_rng(7))]}
    for name, folder in SKERKI.items():
        imgs = read_folder(data / folder, n) if (data / folder).is_dir() else []
        if imgs:
            out[name] = imgs
    for folder in folders:
        out[f"{folder.resolve().parent.name}/{folder.resolve().name}"] = read_folder(folder, n)
    return out


def make_pair(images: list[np.ndarray], n: int, cond: Condition, rng: np.random.Generator
              ) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float, float]]:
    """A reference crop, the moving image and the truth (angle deg, scale, dx, dy), perturbed by ``cond``."""
    src = images[int(rng.integers(len(images)))]
    angle = float(rng.uniform(-180.0, 180.0))
    scale = math.exp(rng.uniform(math.log(0.8), math.log(1.25)))
    dx, dy = (rng.uniform(-cond.max_shift, cond.max_shift, 2) * n).tolist()
    y, x = int(rng.integers(0, src.shape[0] - n + 1)), int(rng.integers(0, src.shape[1] - n + 1))
    a = cv2.getRotationMatrix2D(((n - 1) / 2.0, (n - 1) / 2.0), angle, scale)
    a[:, 2] += (dx, dy)
    a[:, 2] -= a[:, :2] @ np.array([x, y], float)  # source pixel -> moving pixel
    mov = cv2.warpAffine(src, a, (n, n), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).astype(np.float32)
    ref = src[y:y + n, x:x + n].astype(np.float32)
    if cond.blur:
        mov = cv2.GaussianBlur(mov, (0, 0), cond.blur)
    if cond.illumination:
        yy, xx = (np.mgrid[0:n, 0:n] / n) - 0.5
        phi = rng.uniform(0.0, 2.0 * math.pi)
        ramp = 1.0 + 0.4 * (math.cos(phi) * xx + math.sin(phi) * yy)
        mov = (mov * rng.uniform(0.7, 1.3) * ramp + rng.uniform(-20.0, 20.0)).astype(np.float32)
    if cond.noise:
        ref += rng.normal(0.0, cond.noise, ref.shape).astype(np.float32)
        mov += rng.normal(0.0, cond.noise, mov.shape).astype(np.float32)
    return ref, mov, (angle, scale, dx, dy)


def measure(images: list[np.ndarray], n: int, cond: Condition, count: int, seed: int,
            translation_band: int = IfmiConfig().translation_band, lever: str = IfmiConfig().lever
            ) -> dict[str, np.ndarray]:
    """Errors and both covariances of ``count`` pairs (accepted ones only), the translation read from
    ``translation_band`` on."""
    rng = np.random.default_rng(seed)
    paper = IfmiConfig(covariance="paper", translation_band=translation_band)
    calibrated = IfmiConfig(covariance="calibrated", translation_band=translation_band, lever=lever)
    rows: list[list[float]] = []
    for _ in range(count):
        ref, mov, (angle, scale, dx, dy) = make_pair(images, n, cond, rng)
        rp, rc = register(ref, mov, paper), register(ref, mov, calibrated)
        if rp.status is not Status.OK:
            continue
        ea = (rp.angle_deg - angle + 180.0) % 360.0 - 180.0
        rows.append([rp.shift_px[0] - dx, rp.shift_px[1] - dy, ea, rp.scale - scale, rp.scale_var, rc.scale_var,
                     *rp.covariance.ravel(), *rc.covariance.ravel()])
    v = np.array(rows, float).reshape(-1, 24)
    return {"e": v[:, :2], "ea": v[:, 2], "es": v[:, 3], "paper_scale": v[:, 4], "calibrated_scale": v[:, 5],
            "paper": v[:, 6:15].reshape(-1, 3, 3), "calibrated": v[:, 15:24].reshape(-1, 3, 3)}


def stats(m: dict[str, np.ndarray], which: str) -> dict[str, float]:
    """Translation (2 dof) and rotation (1 dof) NEES: mean, median, fraction inside the 95 % band, geometric ratio."""
    c = m[which]
    if not len(c):
        return {}
    t = np.einsum("ni,nij,nj->n", m["e"], np.linalg.inv(c[:, :2, :2]), m["e"])
    r = m["ea"] ** 2 / c[:, 2, 2]
    sc = m["es"] ** 2 / m[f"{which}_scale"]
    out = {}
    for name, v, k in (("t", t, 2), ("r", r, 1), ("s", sc, 1)):
        out.update({f"{name}_mean": float(v.mean()), f"{name}_median": float(np.median(v)),
                    f"{name}_in95": float(np.mean(v <= CHI2_95[k])),
                    f"{name}_gm": float(np.exp(np.mean(np.log(np.maximum(v, 1e-300))))) / GM_CHI2[k]})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=40, help="pairs per source and condition")
    parser.add_argument("--sizes", type=int, nargs="+", default=[256])
    parser.add_argument("--data", type=Path, default=Path(os.environ.get("SLAMREPLAY_DATA", "../shared/data")))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--translation-band", type=int, default=IfmiConfig().translation_band,
                        help="IfmiConfig.translation_band (1: the paper's full band, as before; default %(default)s)")
    parser.add_argument("--lever", choices=LEVERS, default=IfmiConfig().lever,
                        help="IfmiConfig.lever of the calibrated covariance (default %(default)s)")
    parser.add_argument("--images", type=Path, nargs="+", default=[], metavar="DIR",
                        help="more held-out sources: folders of images (png, jpg, bmp, tif, pgm), each at least "
                             "64 px on its smaller side")
    parser.add_argument("--json", type=Path, help="write every row here")
    args = parser.parse_args()
    try:
        IfmiConfig(translation_band=args.translation_band)
    except ValueError as e:
        parser.error(str(e))
    for folder in args.images:
        if not folder.is_dir():
            parser.error(f"--images {folder}: not a folder")
        if not read_folder(folder, 64):
            parser.error(f"--images {folder}: no readable image of at least 64 px in it (png, jpg, bmp, tif, pgm)")
    table: list[dict[str, Any]] = []
    hdr = (f"{'size':>4} {'source':<27} {'condition':<12} {'acc':>7} | {'transl. NEES (2 dof) paper':>26} | "
           f"{'calibrated':>22} | {'rotation NEES (1 dof) paper':>27} | {'calibrated':>22}")
    sub = f"{'':>4} {'':<27} {'':<12} {'':>7} | {'mean  in95':>26} | {'mean  in95    gm':>22} | {'mean  in95':>27} | " \
          f"{'mean  in95    gm':>22}"
    for n in args.sizes:
        print(f"\n{n} x {n}, {args.pairs} pairs per row; chi2 95 % bounds 5.991 (2 dof), 3.841 (1 dof); "
              f"calibrated: mean 2 / 1, in95 0.95, gm 1")
        print(hdr)
        print(sub)
        for source, images in load_sources(args.data, n, tuple(args.images)).items():
            pooled: dict[str, list[np.ndarray]] = {}
            attempted = 0
            for ci, (cname, cond) in enumerate(CONDITIONS.items()):
                m = measure(images, n, cond, args.pairs, args.seed + 1000 * ci + n, args.translation_band,
                            args.lever)
                attempted += args.pairs
                for key, val in m.items():
                    pooled.setdefault(key, []).append(val)
                table.append(_row(n, source, cname, m, args.pairs))
            allm = {k: np.concatenate(v) for k, v in pooled.items()}
            table.append(_row(n, source, "all", allm, attempted))
    if args.json:
        write_json(args.json, {"pairs_per_row": args.pairs, "translation_band": args.translation_band,
                               "lever": args.lever, "rows": table})


def _row(n: int, source: str, cname: str, m: dict[str, np.ndarray], attempted: int) -> dict[str, Any]:
    """Print one table row and return it as a dict."""
    p, c = stats(m, "paper"), stats(m, "calibrated")
    acc = f"{len(m['e'])}/{attempted}"
    if p:
        print(f"{n:>4} {source:<27} {cname:<12} {acc:>7} | {p['t_mean']:20.3f} {p['t_in95']:5.2f} | "
              f"{c['t_mean']:9.2f} {c['t_in95']:5.2f} {c['t_gm']:5.2f} | {p['r_mean']:21.4f} {p['r_in95']:5.2f} | "
              f"{c['r_mean']:9.2f} {c['r_in95']:5.2f} {c['r_gm']:5.2f}")
    return {"size": n, "source": source, "condition": cname, "accepted": len(m["e"]), "attempted": attempted,
            "paper": p, "calibrated": c}


if __name__ == "__main__":
    main()
