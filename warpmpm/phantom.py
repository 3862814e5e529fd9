"""A synthetic abdominal phantom: the built-in default case.

World coordinates follow DICOM/LPS: +x patient left, +y posterior, +z superior (mm).
The phantom holds a curved pancreas (head, body, tail), a duodenal C-loop around the
pancreatic head, a stomach anterior-superior to the pancreatic body and tail, and a left kidney
posterior to the tail, all in contact, inside a body outline with an unlabelled liver and spine
that give an MR-like image texture. Everything is randomised by a seed and deterministic per seed.

Default geometry is like the paper's AMOS MR data (in-plane 1.33 mm, slices 3 mm); with it the
organ particle counts fall inside the paper's ranges (pancreas 7k-72k, stomach 7k-130k,
duodenum 5k-30k, left kidney 21k-125k). ``resolution`` > 1 coarsens the voxels for fast tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .images import PRESETS, Case, Geometry

__all__ = ["INTENSITY", "PhantomConfig", "make_phantom"]

#: Intensities of the synthetic MR-like image (arbitrary units, T1-like contrast).
INTENSITY = {"background": 0.0, "body": 180.0, "liver": 330.0, "spine": 90.0,
             "pancreas": 420.0, "stomach": 240.0, "duodenum": 300.0, "left_kidney": 520.0}


@dataclass(frozen=True)
class PhantomConfig:
    """Phantom settings.

    Attributes:
        seed: random seed; shape, size, position and orientation are drawn from it.
        spacing_mm: voxel size (x, y, z) in mm before ``resolution`` scaling.
        resolution: factor applied to ``spacing_mm`` (2 doubles every voxel edge: ~8x fewer particles).
        noise_sd: standard deviation of the image's Gaussian noise (intensity units).
    """

    seed: int = 0
    spacing_mm: tuple[float, float, float] = (1.33, 1.33, 3.0)
    resolution: float = 1.0
    noise_sd: float = 12.0


def _curve(points: np.ndarray, n: int = 120) -> np.ndarray:
    """A smooth centreline through control points (Catmull-Rom), sampled at ``n`` points."""
    p = np.vstack([points[0], points, points[-1]])
    out = []
    segs = len(points) - 1
    for s in range(segs):
        p0, p1, p2, p3 = p[s], p[s + 1], p[s + 2], p[s + 3]
        for t in np.linspace(0, 1, max(2, n // segs), endpoint=(s == segs - 1)):
            t2, t3 = t * t, t * t * t
            out.append(0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t2 + (-p0 + 3 * p1 - 3 * p2 + p3) * t3))
    return np.asarray(out)


def _tube(grid: tuple[np.ndarray, np.ndarray, np.ndarray], centre: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Mask of points within ``radius[i]`` of centreline point ``centre[i]`` (a swept sphere)."""
    z, y, x = grid
    inside = np.zeros(x.shape, dtype=bool)
    for c, r in zip(centre, radius):
        lo = np.array([c[0] - r, c[1] - r, c[2] - r])
        hi = np.array([c[0] + r, c[1] + r, c[2] + r])
        sx = (x[0, 0, :] >= lo[0]) & (x[0, 0, :] <= hi[0])
        sy = (y[0, :, 0] >= lo[1]) & (y[0, :, 0] <= hi[1])
        sz = (z[:, 0, 0] >= lo[2]) & (z[:, 0, 0] <= hi[2])
        if not (sx.any() and sy.any() and sz.any()):
            continue
        ix, iy, iz = np.nonzero(sx)[0], np.nonzero(sy)[0], np.nonzero(sz)[0]
        sub = (slice(iz[0], iz[-1] + 1), slice(iy[0], iy[-1] + 1), slice(ix[0], ix[-1] + 1))
        d2 = (x[sub] - c[0]) ** 2 + (y[sub] - c[1]) ** 2 + (z[sub] - c[2]) ** 2
        inside[sub] |= d2 <= r * r
    return inside


def _snap(c: np.ndarray, r: np.ndarray, target_c: np.ndarray, target_r: np.ndarray, overlap_mm: float) -> np.ndarray:
    """Translate the tube (c, r) so that it overlaps the target tube by ``overlap_mm`` at the closest pair.

    The pancreas is labelled last, so an overlap becomes a shared boundary: the organs touch.
    """
    d = np.linalg.norm(c[:, None, :] - target_c[None, :, :], axis=2)
    gap = d - r[:, None] - target_r[None, :]
    i, j = np.unravel_index(np.argmin(gap), gap.shape)
    direction = (target_c[j] - c[i]) / max(d[i, j], 1e-9)
    return c + (gap[i, j] + overlap_mm) * direction


def _ellipsoid(grid, centre, radii, yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> np.ndarray:
    z, y, x = grid
    a, b = np.deg2rad(yaw_deg), np.deg2rad(pitch_deg)
    dx, dy, dz = x - centre[0], y - centre[1], z - centre[2]
    u = np.cos(a) * dx + np.sin(a) * dy
    v = -np.sin(a) * dx + np.cos(a) * dy
    u, w = np.cos(b) * u + np.sin(b) * dz, -np.sin(b) * u + np.cos(b) * dz
    return (u / radii[0]) ** 2 + (v / radii[1]) ** 2 + (w / radii[2]) ** 2 <= 1.0


def make_phantom(config: PhantomConfig | None = None, *, seed: int | None = None, resolution: float | None = None,
                 preset: str = "amos") -> Case:
    """Generate the synthetic abdominal phantom as a :class:`~warpmpm.images.Case`.

    Args:
        config: phantom settings (defaults: seed 0, paper-like geometry).
        seed, resolution: shortcuts overriding ``config``.
        preset: label convention of the generated label map (default AMOS, the paper's).
    """
    cfg = config or PhantomConfig()
    if seed is not None or resolution is not None:
        cfg = PhantomConfig(seed if seed is not None else cfg.seed, cfg.spacing_mm,
                            resolution if resolution is not None else cfg.resolution, cfg.noise_sd)
    if cfg.resolution <= 0:
        raise InputError(f"phantom resolution factor must be > 0, got {cfg.resolution}")
    if preset not in PRESETS:
        raise InputError(f"unknown label preset {preset!r}; choose one of {sorted(PRESETS)}")
    rng = np.random.default_rng(cfg.seed)
    spacing = np.asarray(cfg.spacing_mm, dtype=np.float64) * cfg.resolution
    lo = np.array([-110.0, -95.0, -75.0])
    hi = np.array([125.0, 95.0, 95.0])
    size = np.ceil((hi - lo) / spacing).astype(int)
    origin = lo + 0.5 * spacing
    geom = Geometry(tuple(int(s) for s in size), tuple(float(s) for s in spacing), tuple(float(o) for o in origin))
    xs = origin[0] + spacing[0] * np.arange(size[0])
    ys = origin[1] + spacing[1] * np.arange(size[1])
    zs = origin[2] + spacing[2] * np.arange(size[2])
    grid = np.meshgrid(zs, ys, xs, indexing="ij")
    z, y, x = grid

    def jit(scale, n=3):
        return rng.uniform(-scale, scale, n)

    # A global random pose of the organ cluster: small rotation about z and a shift.
    yaw = np.deg2rad(rng.uniform(-8, 8))
    shift = jit(6.0)
    rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])

    def place(p):
        return np.asarray(p, dtype=np.float64) @ rot.T + shift

    size_f = rng.uniform(0.9, 1.1)
    # Pancreas: head (patient right, -x), body anterior to the spine, tail to the left kidney.
    pc = np.array([[-38, -2, -8], [-18, -12, 0], [8, -14, 6], [35, -4, 12], [58, 12, 18]], dtype=np.float64)
    pc[1:4] += rng.uniform(-5, 5, (3, 3))
    pan_c = _curve(place(pc * size_f))
    pan_r = np.interp(np.linspace(0, 1, len(pan_c)), [0, 0.2, 0.45, 1.0], [17, 12, 11, 9]) * size_f * rng.uniform(0.9, 1.1)
    # Duodenum: C-loop around the head (bulb -> descending -> horizontal part).
    dc = np.array([[-22, -34, 22], [-50, -20, 14], [-62, -2, -6], [-56, 8, -30], [-30, 10, -40], [-2, 4, -36]], dtype=np.float64)
    dc[1:5] += rng.uniform(-3, 3, (4, 3))
    duo_c = _curve(place(dc * size_f))
    duo_r = np.full(len(duo_c), 10.0 * size_f * rng.uniform(0.9, 1.1))
    # Stomach: curved sac anterior-superior to the body and tail.
    sc = np.array([[-14, -44, 22], [12, -46, 34], [42, -36, 50], [62, -18, 62]], dtype=np.float64)
    sc += rng.uniform(-4, 4, (4, 3))
    sto_c = _curve(place(sc * size_f))
    sto_r = np.interp(np.linspace(0, 1, len(sto_c)), [0, 0.5, 1.0], [17, 24, 28]) * size_f * rng.uniform(0.9, 1.1)
    # Left kidney: a bean-like tube along the body axis, posterior to the tail.
    tilt = rng.uniform(-0.25, 0.25, 2)
    kc = np.array([[78 + 48 * tilt[0], 38 + 48 * tilt[1], 48], [78, 38, 0], [78 - 48 * tilt[0], 38 - 48 * tilt[1], -48]])
    kid_c = _curve(place(kc * size_f + jit(4.0)), n=80)
    t = np.linspace(-1, 1, len(kid_c))
    kid_r = 25.0 * size_f * rng.uniform(0.9, 1.1) * np.sqrt(np.clip(1 - (0.92 * t) ** 2, 0.05, 1))
    # Neighbours touch the pancreas (a few mm of shared boundary, drawn per seed).
    duo_c = _snap(duo_c, duo_r, pan_c, pan_r, rng.uniform(3.0, 6.0))
    sto_c = _snap(sto_c, sto_r, pan_c, pan_r, rng.uniform(3.0, 6.0))
    kid_c = _snap(kid_c, kid_r, pan_c, pan_r, rng.uniform(3.0, 6.0))

    pancreas = _tube(grid, pan_c, pan_r)
    duodenum = _tube(grid, duo_c, duo_r)
    stomach = _tube(grid, sto_c, sto_r)
    kidney = _tube(grid, kid_c, kid_r)

    body = ((x - 5) / 118) ** 2 + ((y + 5) / 88) ** 2 <= 1.0
    spine = ((x - 0) / 22) ** 2 + ((y - 52) / 20) ** 2 <= 1.0
    liver = _ellipsoid(grid, place(np.array([-70, -10, 40])), np.array([48, 60, 55]))

    lab = PRESETS[preset]
    labels = np.zeros(size[::-1], dtype=np.int32)
    # Stomach first, then the others on top: the pancreas wins where organs would overlap.
    labels[stomach & body] = lab["stomach"]
    labels[kidney & body] = lab["left_kidney"]
    labels[duodenum & body] = lab["duodenum"]
    labels[pancreas & body] = lab["pancreas"]

    image = np.full(labels.shape, INTENSITY["background"], dtype=np.float32)
    image[body] = INTENSITY["body"]
    image[liver & body & (labels == 0)] = INTENSITY["liver"]
    image[spine & (labels == 0)] = INTENSITY["spine"]
    for organ in ("stomach", "left_kidney", "duodenum", "pancreas"):
        image[labels == lab[organ]] = INTENSITY[organ]
    # Smooth texture (a low-frequency bias field) and noise, like a T1 MR scan.
    bias = 1.0 + 0.08 * np.sin(x / 37.0 + rng.uniform(0, 6)) * np.cos(y / 29.0 + rng.uniform(0, 6)) + 0.05 * np.sin(z / 41.0)
    image = image * bias + rng.normal(0.0, cfg.noise_sd, image.shape)
    image[~body] = rng.normal(0.0, cfg.noise_sd * 0.3, int((~body).sum()))
    meta = {"seed": cfg.seed, "resolution": cfg.resolution, "spacing_mm": geom.spacing_mm}
    return Case(labels, geom, dict(lab), image.astype(np.float32), name=f"phantom{cfg.seed}",
                source=f"phantom seed={cfg.seed} resolution={cfg.resolution}", meta=meta)
