"""Fast 2D affine slice registration: Gauss-Newton on normalised intensities (numpy).

The registration module's convention: the forward in-plane motion ``W(x) = A x + t`` takes the stored slice (t-1)
onto the captured slice (t), in the slices' physical mm, and the metric is restricted to a mask on the stored
slice. By default (``domain="captured"``, as ITK's registration samples its fixed image) the sample points are
the captured slice's pixels ``y`` under the mask carried onto it by the initial motion, the stored slice ``S`` is
interpolated at the inverse motion ``V(y) = W^-1(y)``, and ``V`` minimises

    E(V) = sum_y [ S~(V(y)) - I~(y) ]^2,

where ``~`` standardises the intensities over the sampled points (zero mean, unit variance). That is
``2 N (1 - NCC)``, so the minimum is the normalised cross-correlation's maximum, the metric of
:func:`warpmpm.registration.register_slices`, robust to the intensity scaling of MR; ``W = V^-1`` is returned.
Each iteration is a forward-additive Gauss-Newton step: the interpolated slice and its gradient (central
differences) are sampled at ``V(y)``, the Jacobian of the standardised samples is
``J = (G - mean G - S~ mean(S~ G)) / sd(S)`` with ``G = grad S . dV/dp`` (the mean and the spread move with the
warp too), and ``dp = -(J^T J + prior)^-1 (J^T e + prior)`` solves a 6 x 6 system. A pyramid level smooths both
slices by a Gaussian of ``(f - 1) / 2`` pixels, ``f`` the level's factor, and samples every ``f``-th pixel.

What was tried: the inverse-compositional variant (``J`` once from the template: 30 %
faster, but its fixed point is the correlation's maximum only at zero residual); sampling the stored slice's own
pixels (``domain="stored"``: on the MR cine series it left a constant 0.02-0.05 mm a frame that added up along a
series); the exact gradient of the bilinear interpolant (its kinks at pixel edges kept noisy frames cycling and
doubled the frame-to-frame drift).

Why it exists: ITK's registration framework (a regular-step gradient descent over the same metric) spends
most of a cine frame's organ-aware registration in fixed costs and 20-60 first-order iterations on a few
thousand pixels; Gauss-Newton converges in a handful of iterations of a few numpy passes over those pixels:
3.5-4.9x faster on one slice, 3.3-4.3x on a cine frame's organ-aware chain (``benchmarks/registration_speed.py``,
``benchmarks/track_series.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import SimpleITK as sitk

from .errors import InputError

__all__ = ["GaussNewtonConfig", "GaussNewtonResult", "PRIOR_MASK", "ncc", "register_affine_gn"]


@dataclass(frozen=True)
class GaussNewtonConfig:
    """Settings of :func:`register_affine_gn`."""

    levels: tuple[int, ...] = (4, 2, 1)
    """Pyramid factors, coarse to fine: smoothing of ``(f - 1) / 2`` pixels and every ``f``-th template pixel."""
    iterations: int = 30
    """Most Gauss-Newton iterations per level (measured: about 20 over the three levels of a cine frame's
    registration)."""
    tolerance_mm: float = 0.01
    """A level ends when an update moves no corner of the template's bounding box by more than this (mm): a
    fiftieth of a 2 mm cine pixel. (1e-3 mm, tried on the first version, left a third of the cine frames'
    registrations cycling on the noise until the iteration cap, three times the time, for the same error.)"""
    domain: Literal["captured", "stored"] = "captured"
    """Whose pixels are the sample points: ``"captured"`` (the captured slice's pixels whose inverse-mapped position
    falls in the mask, the stored slice interpolated, as ITK's registration samples its fixed image: the inverse
    motion is solved and inverted) or ``"stored"`` (the mask's own pixels, the captured slice interpolated)."""
    linear_prior: float = 0.0
    """Weight of a Tikhonov term ``linear_prior N |A - A0|^2`` (in coordinates scaled by the template's RMS radius,
    N its points) pulling the linear part toward the initial transform's ``A0``: a small footprint fixes its
    translation well and its scale and shear poorly, and the poorly fixed part is what carries the motion to the
    organ's particles away from the slice. 0: none."""
    min_points: int = 30
    """Fewest sample points that must overlap the other slice: fewer at a coarse level leaves that level to the
    finer ones; fewer at the finest ends the registration as not ok (the slice does not overlap the organs)."""
    min_gradient: float = 1e-6
    """Smallest pivot of the Gauss-Newton matrix (relative to its largest): below it the template has no
    structure in some direction (a flat footprint) and the registration is not ok."""

    def __post_init__(self):
        if not self.levels or any(int(f) != f or f < 1 for f in self.levels):
            raise InputError(f"GaussNewtonConfig.levels must be positive integers, got {self.levels}")
        if self.iterations < 1:
            raise InputError(f"GaussNewtonConfig.iterations must be >= 1, got {self.iterations}")
        if not (isinstance(self.linear_prior, (int, float)) and np.isfinite(self.linear_prior) and self.linear_prior >= 0):
            raise InputError(f"GaussNewtonConfig.linear_prior must be a finite number >= 0, got {self.linear_prior!r}")
        if self.domain not in ("captured", "stored"):
            raise InputError(f"GaussNewtonConfig.domain must be 'captured' or 'stored', got {self.domain!r}")
        if not self.tolerance_mm > 0:
            raise InputError(f"GaussNewtonConfig.tolerance_mm must be > 0, got {self.tolerance_mm}")


@dataclass
class GaussNewtonResult:
    """``W(x) = A x + t_mm`` (slice physical mm); ``ncc`` over the template's points at the end (1 is a perfect
    match); ``iterations`` over all levels; ``stop`` why the last level ended; ``ok`` False when it failed."""

    A: np.ndarray
    t_mm: np.ndarray
    ncc: float
    iterations: int
    stop: str
    ok: bool


#: which of the parameters (M00, M01, M10, M11, m0, m1) the linear prior acts on
PRIOR_MASK = np.diag([1.0, 1.0, 1.0, 1.0, 0.0, 0.0])


def _smooth(arr: np.ndarray, sigma_px: float) -> np.ndarray:
    """Separable Gaussian of ``sigma_px`` pixels, edges replicated (shifted-slice sums: on a cine frame's few
    thousand pixels this costs tens of microseconds, where an ITK filter's set-up costs a millisecond)."""
    if sigma_px <= 0:
        return arr
    r = max(1, int(np.ceil(3 * sigma_px)))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma_px) ** 2)
    k /= k.sum()
    out = arr
    for axis in (0, 1):
        n = out.shape[axis]
        pad = np.pad(out, [(r, r) if a == axis else (0, 0) for a in range(2)], mode="edge")
        acc = np.zeros_like(out)
        for j, w in enumerate(k):
            acc += w * (pad[j:j + n] if axis == 0 else pad[:, j:j + n])
        out = acc
    return out


def _bilinear(arr: np.ndarray, ij: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``arr`` (rows = v, columns = u, optionally a trailing channel axis) at continuous pixel indices ``ij``
    (N, 2: column, row); returns the values and which points lie inside (the outside ones read 0)."""
    h, w = arr.shape[:2]
    c, r = ij[:, 0], ij[:, 1]
    inside = (c >= 0) & (c <= w - 1) & (r >= 0) & (r <= h - 1)
    c0 = np.minimum(np.maximum(c.astype(np.intp), 0), max(w - 2, 0))  # truncation = floor for the inside points
    r0 = np.minimum(np.maximum(r.astype(np.intp), 0), max(h - 2, 0))
    fc, fr = np.minimum(np.maximum(c - c0, 0.0), 1.0), np.minimum(np.maximum(r - r0, 0.0), 1.0)
    c1, r1 = np.minimum(c0 + 1, w - 1), np.minimum(r0 + 1, h - 1)
    if arr.ndim == 3:
        fc, fr = fc[:, None], fr[:, None]
    top = arr[r0, c0] * (1 - fc) + arr[r0, c1] * fc
    bot = arr[r1, c0] * (1 - fc) + arr[r1, c1] * fc
    out = top * (1 - fr) + bot * fr
    return np.where(inside[:, None] if arr.ndim == 3 else inside, out, 0.0), inside


def _design(grad: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Steepest-descent rows ``grad . dW/dp`` for the affine ``W(y) = M y + m`` in the order
    (M00, M01, M10, M11, m0, m1); ``grad`` (N, 2) per unit of y."""
    gu, gv = grad[:, 0], grad[:, 1]
    return np.stack([gu * y[:, 0], gu * y[:, 1], gv * y[:, 0], gv * y[:, 1], gu, gv], axis=1)


def _standardise(values: np.ndarray) -> np.ndarray:
    v = values - values.mean()
    sd = float(np.sqrt(np.mean(v * v)))
    return v / sd if sd > 1e-12 else v


def _grid(image: sitk.Image) -> tuple[np.ndarray, np.ndarray]:
    if np.any(np.abs(np.asarray(image.GetDirection()) - np.eye(2).ravel()) > 1e-9):
        raise InputError("the Gauss-Newton slice registration needs axis-aligned 2D slices (identity direction)")
    return np.asarray(image.GetOrigin(), dtype=np.float64), np.asarray(image.GetSpacing(), dtype=np.float64)


def ncc(stored: sitk.Image, captured: sitk.Image, mask: sitk.Image, A: np.ndarray, t_mm: np.ndarray) -> float:
    """Normalised cross-correlation over ``mask``'s pixels (on the stored slice) between the stored slice and the
    captured slice at ``W(x) = A x + t_mm``; points outside the captured slice are left out. 1 is a perfect match."""
    o_s, s_s = _grid(stored)
    o_c, s_c = _grid(captured)
    jj, ii = np.nonzero(sitk.GetArrayViewFromImage(mask))
    if len(ii) == 0:
        return float("nan")
    T = sitk.GetArrayViewFromImage(stored).astype(np.float64)[jj, ii]
    x = o_s + np.stack([ii, jj], axis=1) * s_s
    vals, inside = _bilinear(sitk.GetArrayViewFromImage(captured).astype(np.float64), (x @ np.asarray(A).T + t_mm - o_c) / s_c)
    if inside.sum() < 3:
        return float("nan")
    a, b = _standardise(T[inside]), _standardise(vals[inside])
    return float(np.mean(a * b))


def register_affine_gn(stored: sitk.Image, captured: sitk.Image, mask: sitk.Image, *,
                       initial: tuple[np.ndarray, np.ndarray] | None = None,
                       config: GaussNewtonConfig | None = None) -> GaussNewtonResult:
    """The in-plane affine ``W(x) = A x + t`` taking the stored slice's ``mask`` pixels onto the captured slice
    (module docstring). ``initial``: a starting ``(A, t_mm)`` (e.g. the whole slice's motion for one organ's
    footprint); identity otherwise. Both slices are 2D, axis-aligned, in the same physical mm; the mask is on
    the stored slice's grid. Returns ``ok=False`` (never raises for a bad fit) when too few points overlap, the
    template is flat in some direction, or the result is non-finite or degenerate."""
    cfg = config or GaussNewtonConfig()
    if cfg.domain == "stored":
        return _solve(stored, captured, mask, initial, cfg)
    # on the captured slice's pixels: solve for the inverse motion V = W^-1 (captured -> stored), the mask carried
    # onto the captured grid by the initial motion (nearest neighbour), then invert
    A0, t0 = (np.eye(2), np.zeros(2)) if initial is None else (np.asarray(initial[0], float), np.asarray(initial[1], float))
    Ai = np.linalg.inv(A0)
    tx = sitk.AffineTransform(2)
    tx.SetMatrix(Ai.ravel().tolist())
    tx.SetTranslation((-Ai @ t0).tolist())
    on_captured = sitk.Resample(sitk.Cast(mask, sitk.sitkUInt8), captured, tx, sitk.sitkNearestNeighbor, 0)
    if not np.any(sitk.GetArrayViewFromImage(on_captured)):
        return GaussNewtonResult(np.eye(2), np.zeros(2), float("nan"), 0, "the mask does not overlap the captured slice", False)
    r = _solve(captured, stored, on_captured, (Ai, -Ai @ t0), cfg)
    if not r.ok:
        return r
    A = np.linalg.inv(r.A)
    return GaussNewtonResult(A, -A @ r.t_mm, r.ncc, r.iterations, r.stop, True)


def _solve(stored: sitk.Image, captured: sitk.Image, mask: sitk.Image, initial, cfg: GaussNewtonConfig) -> GaussNewtonResult:
    """The Gauss-Newton iterations with ``stored``'s mask pixels as the sample points (module docstring)."""
    o_s, s_s = _grid(stored)
    o_c, s_c = _grid(captured)
    T0 = sitk.GetArrayFromImage(stored).astype(np.float64)
    I0 = sitk.GetArrayFromImage(captured).astype(np.float64)
    m = sitk.GetArrayViewFromImage(mask) != 0
    if m.shape != T0.shape:
        raise InputError(f"the registration mask has {m.shape[::-1]} pixels, the stored slice {T0.shape[::-1]}")
    jj, ii = np.nonzero(m)
    if len(ii) == 0:
        raise InputError("the registration mask is empty: no organ of the planning contour on this slice")
    x_all = o_s + np.stack([ii, jj], axis=1).astype(np.float64) * s_s
    centre = x_all.mean(axis=0)
    L = max(float(np.sqrt(np.mean(np.sum((x_all - centre) ** 2, axis=1)))), float(s_s.max()))
    # the warp in normalised coordinates y = (x - centre) / L: W~(y) = M[:2, :2] y + M[:2, 2] (homogeneous M, 3 x 3)
    M = np.eye(3)
    if initial is not None:
        A0, t0 = np.asarray(initial[0], dtype=np.float64), np.asarray(initial[1], dtype=np.float64)
        M[:2, :2] = A0
        M[:2, 2] = (A0 @ centre + t0 - centre) / L
    M0 = M.copy()
    lo, hi = x_all.min(axis=0), x_all.max(axis=0)
    corners = (np.array([[lo[0], lo[1]], [lo[0], hi[1]], [hi[0], lo[1]], [hi[0], hi[1]]]) - centre) / L
    total, stop, ok = 0, "no level ran", True
    for f in cfg.levels:
        sigma = (f - 1) / 2.0
        T = _smooth(T0, sigma)
        I = _smooth(I0, sigma)
        # the captured slice and its gradient (per mm, central differences: the exact gradient of the bilinear
        # interpolant was tried and dropped: on noisy cine frames its kinks at pixel edges keep the iterations
        # cycling, and the frame-to-frame drift on the MR series doubled) sampled together, one gather a point
        stack = np.stack([I, np.gradient(I, axis=1) / s_c[0], np.gradient(I, axis=0) / s_c[1]], axis=-1)
        keep = (ii % f == 0) & (jj % f == 0) if f > 1 else np.ones(len(ii), bool)
        if keep.sum() < cfg.min_points:
            keep = np.ones(len(ii), bool)
        y = (x_all[keep] - centre) / L
        tv = T[jj[keep], ii[keep]]
        if float(tv.std()) <= 1e-12:
            return GaussNewtonResult(np.eye(2), np.zeros(2), float("nan"), total, "the template is constant", False)
        if f == cfg.levels[0]:
            tg = np.stack([np.gradient(T, axis=1)[jj[keep], ii[keep]], np.gradient(T, axis=0)[jj[keep], ii[keep]]], axis=1)
            H0 = _design(tg, y)
            w = np.linalg.eigvalsh(H0.T @ H0)
            if not w[0] > cfg.min_gradient * w[-1]:
                return GaussNewtonResult(np.eye(2), np.zeros(2), float("nan"), total,
                                         f"level {f}: the template has no structure in some direction", False)
        stop = f"level {f}: {cfg.iterations} iterations"
        for _ in range(cfg.iterations):
            total += 1
            xw = (y @ M[:2, :2].T + M[:2, 2]) * L + centre
            vals, inside = _bilinear(stack, (xw - o_c) / s_c)
            n_in = int(inside.sum())
            if n_in < cfg.min_points:
                if f != cfg.levels[-1]:  # a coarse level samples every f-th pixel: leave it to the finer ones
                    stop = f"level {f} skipped: only {n_in} sample points overlap the other slice"
                    break
                return GaussNewtonResult(np.eye(2), np.zeros(2), float("nan"), total,
                                         f"level {f}: only {n_in} sample points overlap the other slice", False)
            if n_in < len(inside):
                vals, yy, tt = vals[inside], y[inside], tv[inside]
            else:
                yy, tt = y, tv
            iv = vals[:, 0]
            isd = float(iv.std())
            if isd <= 1e-12:
                return GaussNewtonResult(np.eye(2), np.zeros(2), float("nan"), total,
                                         f"level {f}: the interpolated slice is constant where the sample points land", False)
            iz = (iv - iv.mean()) / isd
            e = iz - _standardise(tt)
            # derivative of the standardised captured values: the warp's, less what the mean and the spread absorb
            J = _design(vals[:, 1:] * L, yy)
            J = (J - J.mean(axis=0) - np.outer(iz, (iz[:, None] * J).mean(axis=0))) / isd
            H, g = J.T @ J, J.T @ e
            if cfg.linear_prior > 0:
                lam = cfg.linear_prior * len(e)
                H = H + lam * PRIOR_MASK
                g = g + lam * PRIOR_MASK @ np.concatenate([(M[:2, :2] - M0[:2, :2]).ravel(), np.zeros(2)])
            try:
                dp = -np.linalg.solve(H, g)
            except np.linalg.LinAlgError:
                ok, stop = False, f"level {f}: the overlapping sample points leave the update undetermined"
                break
            dM = np.array([[dp[0], dp[1], dp[4]], [dp[2], dp[3], dp[5]]])
            move = np.abs(corners @ dM[:, :2].T + dM[:, 2]).max() * L
            M[:2] += dM
            if not np.all(np.isfinite(M)):
                ok, stop = False, f"level {f}: the update is not finite"
                break
            if move < cfg.tolerance_mm:
                stop = f"level {f}: converged (update {move:.2e} mm)"
                break
        if not ok:
            break
    A = M[:2, :2].copy()
    t = L * M[:2, 2] + centre - A @ centre
    if ok and np.all(np.isfinite(A)) and np.all(np.isfinite(t)):
        s = np.linalg.svd(A, compute_uv=False)
        ok = bool(0.5 < s.min() and s.max() < 2.0)
        if not ok:
            stop = f"degenerate result (singular values {s.min():.3f}, {s.max():.3f})"
    else:
        ok = False
    if not ok:
        return GaussNewtonResult(np.eye(2), np.zeros(2), float("nan"), total, stop, False)
    return GaussNewtonResult(A, t, ncc(stored, captured, mask, A, t), total, stop, True)
