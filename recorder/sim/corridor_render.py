"""The world of ``sim-corridor``: textured walls, free space and a ray-casting forward camera.

Walls are the boundary of the floor plan's free space, traced on a 5 cm grid and cut into
panels of the wall's height and about 3/4 of it wide (the textures' aspect). A panel shows a 2 x 2
montage of textures at half size, contrast-equalised (so that an image holds enough corners for
keypoint detectors), or a plain painted wall. Every panel is oriented with the free space on its
right, so a texture reads left to right as seen from the corridor. The camera image is ray cast,
one ray per column, and texture mapped from a mip-mapped atlas of the panels with ``cv2.remap``.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.importers.images import SUFFIXES as IMAGE_SUFFIXES
from slamreplay.recorder.sim.corridor_config import CorridorConfig
from slamreplay.recorder.sim.corridor_plan import floor_plan, route_waypoints

BUILTIN_TEXTURES: Final = Path(__file__).parent / "textures"
TEX_W, TEX_H = 192, 256  # every texture is resized to this (width, height)
MIP_LEVELS: Final = 4
GRID_M: Final = 0.05
ATTENUATION_PER_M: Final = 0.02  # walls darken with distance: 1 / (1 + this * d)
MIN_DEPTH_M: Final = 0.05

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


def load_textures(spec: str) -> list[NDArray[np.uint8]]:
    """Grey (TEX_H, TEX_W) textures of ``spec`` (empty: the built-in ones), sorted by file name."""
    folder = BUILTIN_TEXTURES if not spec else Path(spec)
    if not folder.is_dir():
        raise RecorderError(f"texture folder {spec} does not exist: give a folder of images or '' for the built-in")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    out = []
    for p in files:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is not None:
            img = cv2.resize(img, (TEX_W, TEX_H), interpolation=cv2.INTER_AREA) if img.shape != (TEX_H, TEX_W) else img
            out.append(np.asarray(img, dtype=np.uint8))
    if not out:
        raise RecorderError(f"texture folder {folder} holds no readable images ({', '.join(IMAGE_SUFFIXES)})")
    return out


def trace_walls(rects: list[tuple[float, float, float, float]], cell_m: float = GRID_M) -> tuple[F64, NDArray[np.bool_],
                                                                                                  F64]:
    """Wall segments ``(n, 4)`` [x0, y0, x1, y1] bounding the union of ``rects``, free side on the right.

    Also returns the free-space grid (rows = y) and its origin (x, y) of cell (0, 0)'s corner.
    """
    r = np.asarray(rects, dtype=np.float64)
    origin = np.floor(r[:, :2].min(axis=0) / cell_m) * cell_m - 2 * cell_m
    shape = np.ceil((r[:, 2:].max(axis=0) - origin) / cell_m).astype(int) + 2
    xc = origin[0] + (np.arange(shape[0]) + 0.5) * cell_m
    yc = origin[1] + (np.arange(shape[1]) + 0.5) * cell_m
    free = np.zeros((shape[1], shape[0]), dtype=bool)
    for x0, y0, x1, y1 in r:
        free[np.ix_((yc > y0) & (yc < y1), (xc > x0) & (xc < x1))] = True
    segs: list[tuple[float, float, float, float]] = []
    # Horizontal edges between rows j-1 and j; free above -> the wall runs -x (free on its right).
    change = free[1:, :].astype(np.int8) - free[:-1, :].astype(np.int8)
    for j, i0, i1, sign in _runs(change):
        y = origin[1] + (j + 1) * cell_m
        xa, xb = origin[0] + i0 * cell_m, origin[0] + i1 * cell_m
        segs.append((xb, y, xa, y) if sign > 0 else (xa, y, xb, y))
    # Vertical edges between columns i-1 and i; free to the right (+x) -> the wall runs +y.
    change = free[:, 1:].astype(np.int8) - free[:, :-1].astype(np.int8)
    for i, j0, j1, sign in _runs(change.T):
        x = origin[0] + (i + 1) * cell_m
        ya, yb = origin[1] + j0 * cell_m, origin[1] + j1 * cell_m
        segs.append((x, ya, x, yb) if sign > 0 else (x, yb, x, ya))
    return np.array(segs), free, origin


def _runs(change: NDArray[np.int8]) -> list[tuple[int, int, int, int]]:
    """Maximal runs of equal non-zero values along each row: (row, start, end (exclusive), sign)."""
    out = []
    for row in np.flatnonzero(np.any(change != 0, axis=1)):
        line = np.concatenate([[0], change[row], [0]])
        edges = np.flatnonzero(np.diff(line) != 0)
        for a, b in itertools.pairwise(edges):
            if line[a + 1] != 0:
                out.append((int(row), int(a), int(b), int(line[a + 1])))
    return out


def build_atlas(textures: list[NDArray[np.uint8]]) -> NDArray[np.uint8]:
    """Textures side by side, with ``MIP_LEVELS`` halvings stacked below (level l starts at row oy(l))."""
    base = np.hstack(textures)
    levels = [base]
    for _ in range(1, MIP_LEVELS):
        prev = levels[-1]
        levels.append(np.asarray(cv2.resize(prev, (prev.shape[1] // 2, prev.shape[0] // 2),
                                            interpolation=cv2.INTER_AREA), dtype=np.uint8))
    atlas = np.zeros((sum(lv.shape[0] for lv in levels), base.shape[1]), np.uint8)
    row = 0
    for lv in levels:
        atlas[row:row + lv.shape[0], :lv.shape[1]] = lv
        row += lv.shape[0]
    return atlas


class CorridorWorld:
    """The walls, the free space, the route and the camera of a ``sim-corridor`` world.

    Build it with :meth:`from_config`; the same ``(config, seed)`` gives the same world.

    Attributes
    ----------
    config, seed : what built it.
    walls : (n, 4) float64 wall panels ``[x0, y0, x1, y1]`` in metres (``world`` frame), free side on
        the right of the direction (x0, y0) -> (x1, y1).
    panel_tiles : (n, 4) int64 texture index of each panel's quarters (top left, top right, bottom
        left, bottom right), -1 for a plain painted panel. Equal rows look alike.
    route : (m, 2) float64 waypoints of the teleoperated route, starting at the origin.
    """

    def __init__(self, config: CorridorConfig, seed: int, textures: list[NDArray[np.uint8]]) -> None:
        self.config, self.seed = config, int(seed)
        rng = np.random.default_rng(self.seed).spawn(4)[0]  # stream 0 of the simulator's seed: the world
        self.rects = floor_plan(config.corridor_width_m)
        long_walls, self._free, self._origin = trace_walls(self.rects)
        self.textures = textures
        self.walls, self.panel_tiles, gain = self._panels(long_walls, rng)
        self.route = route_waypoints(config.route, config.laps)
        self._atlas = build_atlas(self._looks(rng))
        d = self.walls[:, 2:] - self.walls[:, :2]
        self._seg_len = np.hypot(d[:, 0], d[:, 1])
        facing_x = np.abs(d[:, 1]) > np.abs(d[:, 0])  # walls across the x axis are lit a little less
        self._gain = (gain * np.where(facing_x, 0.88, 1.0)).astype(np.float32)
        self._background = self._floor_and_ceiling()
        # A bank of unit sensor noise; each image adds a random window of it (drawing fresh noise would
        # cost more than the rendering).
        self._noise = rng.standard_normal((2 * config.image_height, 2 * config.image_width), dtype=np.float32)
        self._rows = np.arange(config.image_height, dtype=np.float32)[:, None]

    @classmethod
    def from_config(cls, config: CorridorConfig, seed: int) -> CorridorWorld:
        """The world of ``(config, seed)``; RecorderError when the textures cannot be read."""
        return cls(config, seed, load_textures(config.texture))

    def to_json(self) -> str:
        """``{"config": {...}, "seed": N}``: all it takes to rebuild this world (:meth:`from_json`)."""
        return json.dumps({"config": dataclasses.asdict(self.config), "seed": self.seed}, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> CorridorWorld:
        """The world named by :meth:`to_json`'s output."""
        spec = json.loads(text)
        return cls.from_config(CorridorConfig.from_dict(spec.get("config", {})), int(spec["seed"]))

    def describe(self) -> dict[str, Any]:
        """A short JSON-able description for a recording's metadata."""
        lo, hi = self.walls[:, :2].min(axis=0), self.walls[:, :2].max(axis=0)
        return {"panels": len(self.walls), "textures": len(self.textures), "bounds_m": [*lo.round(2).tolist(),
                *hi.round(2).tolist()], "route_waypoints": len(self.route)}

    def _panels(self, long_walls: F64, rng: np.random.Generator) -> tuple[F64, NDArray[np.int64], F64]:
        """Cut walls into panels about as wide as a texture at the wall's height; pick their tiles and gains."""
        width = self.config.wall_height_m * TEX_W / TEX_H
        panels = []
        for x0, y0, x1, y1 in long_walls:
            n = max(1, round(math.hypot(x1 - x0, y1 - y0) / width))
            t = np.linspace(0.0, 1.0, n + 1)
            for a, b in itertools.pairwise(t):
                panels.append((x0 + a * (x1 - x0), y0 + a * (y1 - y0), x0 + b * (x1 - x0), y0 + b * (y1 - y0)))
        n = len(panels)
        tiles = rng.integers(0, len(self.textures), (n, 4))
        tiles[rng.random(n) < self.config.plain_fraction] = -1
        gain = rng.uniform(0.85, 1.15, n)
        # Twins: copy a run of three panels onto another one elsewhere (perceptual aliasing).
        for _ in range(self.config.twins if n >= 6 else 0):
            a, b = rng.choice(n - 2, 2, replace=False)
            tiles[b:b + 3], gain[b:b + 3] = tiles[a:a + 3], gain[a:a + 3]
        return np.array(panels), tiles.astype(np.int64), gain

    def _looks(self, rng: np.random.Generator) -> list[NDArray[np.uint8]]:
        """One (TEX_H, TEX_W) image per panel: a contrast-equalised 2 x 2 montage, or a plain painted wall."""
        half = [cv2.resize(t, (TEX_W // 2, TEX_H // 2), interpolation=cv2.INTER_AREA) for t in self.textures]
        clahe = cv2.createCLAHE(clipLimit=4.0, tileGridSize=(8, 8))
        blotch = cv2.GaussianBlur(rng.standard_normal((TEX_H, TEX_W)), (0, 0), 12.0)
        plain = np.clip(168.0 + 6.0 * blotch / blotch.std() + 1.5 * rng.standard_normal((TEX_H, TEX_W)), 0, 255)
        cache: dict[tuple[int, ...], NDArray[np.uint8]] = {}
        looks = []
        for row in self.panel_tiles:
            key = tuple(int(k) for k in row)
            if key not in cache:
                cache[key] = plain.astype(np.uint8) if key[0] < 0 else np.asarray(clahe.apply(np.vstack([
                    np.hstack([half[key[0]], half[key[1]]]), np.hstack([half[key[2]], half[key[3]]])])), dtype=np.uint8)
            looks.append(cache[key])
        return looks

    def _floor_and_ceiling(self) -> F32:
        """Plain shading: the ceiling bright under lights, the floor darker, both fading to the horizon."""
        cfg = self.config
        f, cy = cfg.focal_px, 0.5 * (cfg.image_height - 1)
        v = np.arange(cfg.image_height, dtype=np.float64) - cy
        with np.errstate(divide="ignore"):
            floor_d = np.where(v > 0, cfg.camera_height_m * f / np.maximum(v, 1e-9), np.inf)
            ceil_d = np.where(v < 0, (cfg.wall_height_m - cfg.camera_height_m) * f / np.maximum(-v, 1e-9), np.inf)
        floor = 70.0 + 50.0 / (1.0 + ATTENUATION_PER_M * 3 * floor_d)
        ceil = 120.0 + 80.0 / (1.0 + ATTENUATION_PER_M * 3 * ceil_d)
        col = np.where(v > 0, floor, ceil)
        return np.repeat(col[:, None], cfg.image_width, axis=1).astype(np.float32)

    def ray_cast(self, pose: ArrayLike) -> tuple[F64, NDArray[np.int64], F64]:
        """Cast one ray per image column from ``pose`` ``[x_m, y_m, yaw_rad]``.

        Returns
        -------
        depth : (W,) perpendicular distance to the wall hit (inf where none), metres.
        panel : (W,) index into :attr:`walls` of the panel hit (-1 where none).
        along : (W,) where along that panel, 0 at (x0, y0) to 1 at (x1, y1).
        """
        x, y, yaw = (float(v) for v in np.asarray(pose, dtype=np.float64).reshape(3))
        cfg = self.config
        cols = np.arange(cfg.image_width, dtype=np.float64)
        ang = np.arctan((0.5 * (cfg.image_width - 1) - cols) / cfg.focal_px)  # the camera's left is +y
        rx, ry = np.cos(yaw + ang)[:, None], np.sin(yaw + ang)[:, None]
        ax, ay = self.walls[None, :, 0] - x, self.walls[None, :, 1] - y
        ex, ey = (self.walls[:, 2] - self.walls[:, 0])[None, :], (self.walls[:, 3] - self.walls[:, 1])[None, :]
        den = rx * ey - ry * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ax * ey - ay * ex) / den
            s = (ax * ry - ay * rx) / den
        t = np.where((den != 0) & (t > 1e-9) & (s >= 0) & (s <= 1), t, np.inf)
        panel = np.argmin(t, axis=1)
        rows = np.arange(len(cols))
        dist = t[rows, panel]
        hit = np.isfinite(dist)
        return dist * np.cos(ang), np.where(hit, panel, -1), np.where(hit, s[rows, panel], 0.0)

    def render(self, pose: ArrayLike, rng: np.random.Generator | None = None) -> NDArray[np.uint8]:
        """The (H, W) mono8 image of the forward camera at the true ``pose`` ``[x_m, y_m, yaw_rad]``.

        Without ``rng`` the image is noise-free; with it, a global gain of ``brightness_jitter``
        and Gaussian noise of ``noise_sigma`` grey levels (a window, at an offset drawn from ``rng``,
        of a noise bank made with the world) are added: three draws from ``rng`` per image.
        """
        cfg = self.config
        depth, panel, along = self.ray_cast(pose)
        hit = panel >= 0
        depth = np.maximum(np.where(hit, depth, 1e6), MIN_DEPTH_M)
        p = np.where(hit, panel, 0)
        tu = along * TEX_W  # texel column at level 0
        # Texels per image pixel, vertically and across: picks the mip level (against aliasing).
        b = TEX_H * depth / (cfg.focal_px * cfg.wall_height_m)  # d(texel row) / d(image row)
        same = np.gradient(p.astype(np.float64)) == 0  # not at a panel's edge
        across = np.where(same, np.abs(np.gradient(tu)), 0.0)
        level = np.clip(np.floor(np.log2(np.maximum(np.maximum(b, across), 1e-6)) + 0.3), 0, MIP_LEVELS - 1)
        scale = 2.0**level
        oy = TEX_H * (2.0 - 2.0 ** (1.0 - level))
        x0 = p * TEX_W / scale
        map_x = np.clip(x0 + tu / scale - 0.5, x0, x0 + TEX_W / scale - 1.0).astype(np.float32)
        # Texel row of image row v: tv = a + b v, 0 at the wall top and TEX_H at the floor; in the atlas
        # oy + tv / scale - 0.5 at mip level l, clamped inside the level.
        a = TEX_H * (1.0 - cfg.camera_height_m / cfg.wall_height_m) - b * 0.5 * (cfg.image_height - 1)
        rows = self._rows
        map_y = rows * (b / scale).astype(np.float32) + (oy - 0.5 + a / scale).astype(np.float32)
        np.clip(map_y, oy.astype(np.float32), (oy + TEX_H / scale - 1.0).astype(np.float32), out=map_y)
        v_top = np.where(hit, -a / b, np.inf).astype(np.float32)
        wall = (rows >= v_top) & (rows <= ((TEX_H - a) / b).astype(np.float32))
        tex = cv2.remap(self._atlas, np.ascontiguousarray(np.broadcast_to(map_x, map_y.shape)), map_y,
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        shade = self._gain[p] / (1.0 + ATTENUATION_PER_M * depth)
        background = self._background
        if rng is not None:
            gain = 1.0 + cfg.brightness_jitter * float(rng.standard_normal())
            shade, background = shade * gain, background * np.float32(gain)
        img = np.where(wall, tex * shade.astype(np.float32), background)
        if rng is not None:
            i, j = rng.integers(0, [cfg.image_height + 1, cfg.image_width + 1])
            img = cv2.scaleAdd(self._noise[i:i + cfg.image_height, j:j + cfg.image_width], cfg.noise_sigma, img)
        out = cv2.add(img, 0.0, dtype=cv2.CV_8U)  # type: ignore[call-overload]  # rounded, saturated to [0, 255]
        return np.asarray(out, dtype=np.uint8)

    def is_free(self, xy: ArrayLike, clearance_m: float = 0.0) -> bool:
        """Whether the point ``xy`` (metres) is in free space at least ``clearance_m`` from every wall."""
        return bool(self.free_mask(np.asarray(xy, dtype=np.float64).reshape(1, 2), clearance_m)[0])

    def free_mask(self, xy: ArrayLike, clearance_m: float = 0.0) -> NDArray[np.bool_]:
        """:meth:`is_free` of each row of an ``(n, 2)`` array of points."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        ij = np.floor((pts - self._origin) / GRID_M).astype(np.int64)
        inside = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < self._free.shape[1]) & (ij[:, 1] < self._free.shape[0])
        ok = np.zeros(len(pts), dtype=bool)
        ok[inside] = self._free[ij[inside, 1], ij[inside, 0]]
        if clearance_m > 0 and np.any(ok):
            a, e = self.walls[:, :2], self.walls[:, 2:] - self.walls[:, :2]
            rel = pts[ok, None, :] - a[None]
            s = np.clip((rel * e[None]).sum(-1) / (e * e).sum(-1)[None], 0.0, 1.0)
            dist = np.hypot(*(rel - s[..., None] * e[None]).transpose(2, 0, 1)).min(axis=1)
            ok[ok] = dist >= clearance_m
        return ok
