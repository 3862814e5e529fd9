"""Scores of every organ, and the baselines that copy what the planes see organ by organ.

Every method of a run is scored on each organ of the model: the pancreas (the target) and the stomach,
duodenum and left kidney (organs at risk). An organ is *seen* when a driving plane holds at least
:data:`MIN_SEEN` of its particles; its particles are split into those on a plane (told their in-plane motion)
and those off every plane (inferred). The distance that a dose decision depends on, the smallest distance
between the pancreas and each organ at risk, is reported estimated against true.

Baselines with the same information as the estimate (the planes' observed in-plane motion):

- ``rigid``: each seen organ moved by its mean observed translation, the planes combined (each plane gives its
  in-plane components; least squares where planes share a direction; a direction no plane measures stays
  still): what MR-Linac tracking does today. An organ no plane crosses stays where it was.
- ``nearest``: each organ no plane crosses moved by the ``rigid`` translation of the seen organ nearest to it.
- ``global``: each organ no plane crosses moved by the mean observed translation of everything the planes see.

``nearest`` and ``global`` score only the organs no plane crosses (their pancreas figures are NaN when the
pancreas is seen).
"""

from __future__ import annotations

import numpy as np

from ..model import ParticleModel

__all__ = ["MIN_SEEN", "ORGANS_AT_RISK", "observed_translation", "seen_organs", "organ_translations", "nearest_seen",
           "baseline_positions", "true_distances", "organ_scores", "format_organ_table"]

#: Fewest particles of an organ on the driving planes for it to count as seen.
MIN_SEEN = 10

#: Organs at risk of the model, whose distance to the pancreas is reported.
ORGANS_AT_RISK = ("stomach", "duodenum", "left_kidney")


def observed_translation(axes: np.ndarray, displacement_mm: np.ndarray) -> np.ndarray:
    """The translation ``t`` that best explains observed displacements ``d_i`` each seen through a projector
    ``A_i``: ``t = pinv(sum A_i) sum A_i d_i`` (zero along directions no projector measures)."""
    if len(axes) == 0:
        return np.zeros(3)
    span = axes.sum(0)
    num = np.einsum("nij,nj->i", axes, displacement_mm)
    return np.linalg.pinv(span, rcond=1e-6) @ num


def seen_organs(model: ParticleModel, idx: np.ndarray) -> dict[str, np.ndarray]:
    """Organ -> positions in ``idx`` of its driven particles, for the organs the planes see."""
    organ_of = model.organ_index[idx]
    out = {}
    for k, o in enumerate(model.organs):
        sel = np.nonzero(organ_of == k)[0]
        if len(sel) >= MIN_SEEN:
            out[o] = sel
    return out


def organ_translations(model: ParticleModel, idx: np.ndarray, targets_mm: np.ndarray, axes: np.ndarray) -> dict[str, np.ndarray]:
    """Each seen organ's observed translation (the ``rigid`` baseline's), and ``"_all"``: everything seen."""
    d = targets_mm - model.positions_mm[idx]
    out = {o: observed_translation(axes[sel], d[sel]) for o, sel in seen_organs(model, idx).items()}
    out["_all"] = observed_translation(axes, d)
    return out


def _min_distance(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    if len(a) == 0 or len(b) == 0:
        return float("nan")
    d, _ = cKDTree(b).query(a, k=1)
    return float(d.min())


def nearest_seen(model: ParticleModel, organ: str, seen: list[str]) -> str | None:
    """The seen organ closest to ``organ`` at planning (smallest particle-to-particle distance)."""
    if not seen:
        return None
    x = model.positions_mm
    a = x[model.organ_slice(organ)][::4]
    return min(seen, key=lambda o: _min_distance(a, x[model.organ_slice(o)][::4]))


def baseline_positions(model: ParticleModel, idx: np.ndarray, targets_mm: np.ndarray, axes: np.ndarray) -> dict[str, np.ndarray]:
    """Positions (N, 3) under ``rigid``, and under ``nearest`` / ``global`` when some organ is on no plane."""
    t = organ_translations(model, idx, targets_mm, axes)
    seen = [o for o in model.organs if o in t]
    unseen = [o for o in model.organs if o not in t]
    x = model.positions_mm
    rigid = x.copy()
    for o in seen:
        rigid[model.organ_slice(o)] += t[o]
    out = {"rigid": rigid}
    if unseen and seen:
        near, glob = rigid.copy(), rigid.copy()
        for o in unseen:
            sel = model.organ_slice(o)
            near[sel] = x[sel] + t[nearest_seen(model, o, seen)]
            glob[sel] = x[sel] + t["_all"]
        out["nearest"], out["global"] = near, glob
    return out


def true_distances(model: ParticleModel, truth_mm: np.ndarray) -> dict[str, float]:
    """Each organ at risk's smallest distance to the pancreas in the truth (mm): the same for every method of a run."""
    if "pancreas" not in model.organs:
        return {}
    pan = model.organ_slice("pancreas")
    return {o: _min_distance(truth_mm[pan], truth_mm[model.organ_slice(o)]) for o in model.organs if o in ORGANS_AT_RISK}


def organ_scores(model: ParticleModel, positions_mm: np.ndarray, truth_mm: np.ndarray, on_plane: np.ndarray,
                 only: list[str] | None = None, truth_distances: dict | None = None) -> dict[str, dict]:
    """Per organ: ``error_mm`` (mean over all its particles), ``p95_mm``, ``max_mm``, ``on_plane_mm`` and
    ``off_plane_mm`` (its particles on a driving plane and off every plane; NaN when there are none), the mean
    absolute error along ``lr_mm`` / ``ap_mm`` / ``si_mm`` (world x, y, z), ``seen`` (on a plane), ``n``; for each
    organ at risk ``distance_to_pancreas_mm`` (smallest distance, estimated), ``true_distance_to_pancreas_mm`` and
    ``distance_error_mm`` (estimated minus true). ``only``: score just these organs. ``truth_distances``: the truth's
    distances (:func:`true_distances`), when a run scores several methods against one truth."""
    err = positions_mm - truth_mm
    dist = np.linalg.norm(err, axis=1)
    pan = model.organ_slice("pancreas") if "pancreas" in model.organs else None
    if truth_distances is None:
        truth_distances = true_distances(model, truth_mm)
    out = {}
    for o in model.organs:
        if only is not None and o not in only:
            continue
        sel = model.organ_slice(o)
        on = sel & on_plane
        off = sel & ~on_plane
        d = dist[sel]
        r = {"error_mm": float(d.mean()), "p95_mm": float(np.percentile(d, 95)), "max_mm": float(d.max()),
             "on_plane_mm": float(dist[on].mean()) if on.any() else float("nan"),
             "off_plane_mm": float(dist[off].mean()) if off.any() else float("nan"),
             "lr_mm": float(np.abs(err[sel, 0]).mean()), "ap_mm": float(np.abs(err[sel, 1]).mean()),
             "si_mm": float(np.abs(err[sel, 2]).mean()), "seen": bool(np.count_nonzero(on) >= MIN_SEEN), "n": int(sel.sum())}
        if o in ORGANS_AT_RISK and pan is not None:
            est = _min_distance(positions_mm[pan], positions_mm[sel])
            true = truth_distances[o]
            r |= {"distance_to_pancreas_mm": est, "true_distance_to_pancreas_mm": true, "distance_error_mm": est - true}
        out[o] = r
    return out


def format_organ_table(results: dict) -> str:
    """Markdown: one row per (method, organ) with the organ's error, on/off-plane split, p95, SI error and the
    pancreas distance error."""
    rows = ["| method | organ | seen | error mm | on plane mm | off plane mm | p95 mm | SI error mm | distance to pancreas: est / true mm |",
            "|---|---|---|---|---|---|---|---|---|"]
    est = results.get("estimate")
    chosen = next((n for n, r in results.items() if r is est and n != "estimate"), None)
    for name, r in results.items():
        if r is est and name != "estimate":
            continue  # the estimator that is the estimate: one row, named on the estimate's
        organs = getattr(r, "organs", None) or {}
        if name == "estimate" and chosen:
            name = f"estimate ({chosen})"
        for o, s in organs.items():
            dist = (f"{s['distance_to_pancreas_mm']:.1f} / {s['true_distance_to_pancreas_mm']:.1f}"
                    if "distance_to_pancreas_mm" in s else "")
            rows.append(f"| {name} | {o} | {'yes' if s['seen'] else 'no'} | {s['error_mm']:.2f} | {s['on_plane_mm']:.2f} | "
                        f"{s['off_plane_mm']:.2f} | {s['p95_mm']:.2f} | {s['si_mm']:.2f} | {dist} |")
    return "\n".join(rows)
