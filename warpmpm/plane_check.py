"""Checking each plane's registered motion against what the images show, before it drives anything.

A slice registration can fail while passing its own checks: on the MR sample under a large contact deformation the
sagittal + coronal registrations moved the pancreas 16 mm superior where it moved 3 mm inferior, and the estimate
driven by them ended 18 mm off against 9.5 mm for no motion at all. The registrations' metric looks at one plane at a
time; this check looks at every plane at once, with the motion each plane's organs bring to the whole body.

**The measure** (no truth used): the planning image moved by a motion (every particle's displacement, smoothed into a
field: :func:`warpmpm.imaging.warp_array`) is cut on every captured plane and compared with the captured image by
normalised cross-correlation over a fixed region of that plane (the organs' planning footprint dilated by
:data:`REGION_MM`); the plane match of a motion is the mean over the planes. No motion scores the planning image
itself.

**The check.** Every (plane, organ) pair seen on a plane brings that organ's registered motion (propagated to the
organ's particles, combined in the least-squares sense where planes share a direction, as ``propagate_planes``):

1. a pair whose motion is larger than a frame could show (mean over the organ over :data:`MAX_MOTION_MM`) is dropped;
2. two planes that disagree on the motion they share (the superior-inferior motion of an organ seen on a sagittal
   and a coronal plane differing by more than :data:`DISAGREE_MM`) are reported;
3. starting from every remaining pair, the pair whose removal raises the plane match most is dropped, while a removal
   raises it by more than :data:`MIN_GAIN` (backward elimination); then, if no motion at all matches the planes better
   than what is kept, every pair is dropped.

A dropped pair is never driven: its particles take no target from that plane (a particle on two planes keeps the
other's). Each drop is one warning line naming the plane, the organ and the figures.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from .errors import InputWarning
from .imaging import capture_slice, slice_mask, warp_array
from .metrics import correlation
from .model import ParticleModel
from .slices import DrivingSlice, extract_slice
from .targets import plane_projector

__all__ = ["PlaneCheck", "check_planes", "plane_match", "combined_motion", "REGION_MM", "MAX_MOTION_MM", "DISAGREE_MM", "MIN_GAIN"]

#: the compared region of a plane: the organs' planning footprint dilated by this much (mm)
REGION_MM = 10.0
#: an organ's mean registered motion above this (mm) is more than a cine frame shows of abdominal organs (breathing
#: moves them 10-25 mm)
MAX_MOTION_MM = 35.0
#: planes disagreeing by more than this (mm) on an organ's shared superior-inferior motion are reported
DISAGREE_MM = 5.0
#: a removal must raise the mean plane correlation by more than this to be made
MIN_GAIN = 0.005


@dataclass
class PlaneCheck:
    """What the check found.

    Attributes:
        kept, dropped: (plane name, organ) pairs; reasons: pair -> why it was dropped (with the figures).
        match_none, match_all, match_kept: the plane match (mean correlation over the planes) of no motion, of every
        pair's motion, of the kept pairs' motion. disagreements: (organ, SI motion on each plane, mm) reported.
        worse_than_none: True when even the kept motion matches the planes worse than no motion (then nothing is kept).
    """

    kept: list = field(default_factory=list)
    dropped: list = field(default_factory=list)
    reasons: dict = field(default_factory=dict)
    match_none: float = float("nan")
    match_all: float = float("nan")
    match_kept: float = float("nan")
    disagreements: list = field(default_factory=list)
    evaluations: int = 0

    def to_json(self) -> dict:
        return {"kept": [f"{p}/{o}" for p, o in self.kept], "dropped": {f"{p}/{o}": r for (p, o), r in self.reasons.items()},
                "match_none": self.match_none, "match_all": self.match_all, "match_kept": self.match_kept,
                "disagreements": self.disagreements, "evaluations": self.evaluations}


class _Planes:
    """The captured planes and their fixed comparison regions; scores a motion of every particle."""

    def __init__(self, model, slices, planning_volume, captured_volume, labels, geometry, label_values, centre_mm, name,
                 noise_sd=0.0, in_plane_factor=1.0):
        self.model, self.slices, self.planning, self.geometry, self.centre = model, slices, planning_volume, geometry, centre_mm
        values = [label_values[o] for o in model.organs]
        self.regions, self.captured = [], []
        for s in slices:
            m = sitk_array(slice_mask(labels, geometry, s.orientation, s.index, centre_mm, values, dilate_mm=REGION_MM)) > 0
            cap = sitk_array(capture_slice(captured_volume, geometry, s.orientation, s.index, centre_mm, noise_sd=noise_sd,
                                           in_plane_factor=in_plane_factor))
            self.regions.append(m)
            self.captured.append(cap[m].astype(np.float64))
        self.name = name
        self.evaluations = 0

    def per_plane(self, positions_mm) -> list[float]:
        self.evaluations += 1
        x0 = self.model.positions_mm
        vol = self.planning if positions_mm is None else warp_array(self.planning, self.geometry, x0, positions_mm)
        out = []
        for s, m, cap in zip(self.slices, self.regions, self.captured):
            ren = sitk_array(extract_slice(vol, self.geometry, s.orientation, s.index, self.centre))[m].astype(np.float64)
            out.append(correlation(ren, cap))
        return out

    def match(self, positions_mm) -> float:
        return float(np.mean(self.per_plane(positions_mm)))


def sitk_array(img) -> np.ndarray:
    import SimpleITK as sitk

    return sitk.GetArrayFromImage(img)


def combined_motion(model: ParticleModel, positions_mm, slices, moved, keep) -> np.ndarray:
    """Every particle moved by the pairs ``keep(s, idx)`` lets through (:func:`_combined`)."""
    organ_of = np.asarray(model.organs)[model.organ_index]
    pairs = [(s, o) for s in slices for o in model.organs
             if np.any(organ_of == o) and keep(s, np.nonzero(organ_of == o)[0][:1])[0]]
    return _combined(model, np.asarray(positions_mm, dtype=np.float64), slices, moved, pairs)


def _combined(model: ParticleModel, positions_mm, slices, moved, pairs) -> np.ndarray:
    """Every particle moved by the kept pairs' motion: each plane's motion of its kept organs (all their particles), in
    the plane's directions, averaged where planes share a direction; no motion from a plane for its other organs."""
    organ_of = np.asarray(model.organs)[model.organ_index]
    everyone = np.arange(model.n)
    num, span = np.zeros((model.n, 3)), np.zeros((model.n, 3, 3))
    for s in slices:
        organs = [o for (p, o) in pairs if p == s]
        if not organs:
            continue
        sel = np.isin(organ_of, organs)
        P = plane_projector(model, s.orientation)
        d = np.zeros((model.n, 3))
        d[sel] = (moved(s, everyone[sel]) - positions_mm[sel]) @ P.T
        num += d
        span[sel] += P
    out = positions_mm.copy()
    has = np.abs(span).sum(axis=(1, 2)) > 0
    out[has] += np.einsum("nij,nj->ni", np.linalg.pinv(span[has], rcond=1e-6), num[has])
    return out


def plane_match(model, slices, planning_volume, captured_volume, labels, geometry, label_values, centre_mm, positions_mm,
                **capture) -> list[float]:
    """Per plane, the correlation of the captured plane with the planning image moved by ``positions_mm`` (None: not
    moved) over the plane's organ region: the measure of the module docstring."""
    return _Planes(model, slices, planning_volume, captured_volume, labels, geometry, label_values, centre_mm, str,
                   **capture).per_plane(positions_mm)


def check_planes(model: ParticleModel, slices: list[DrivingSlice], moved, planning_volume, captured_volume, labels, geometry,
                 label_values, centre_mm, *, positions_mm=None, name=str, warn: bool = True, **capture) -> tuple[PlaneCheck, callable]:
    """Check each (plane, organ) pair's registered motion (module docstring).

    ``moved(s, idx)``: the registered positions of particles ``idx`` under slice ``s``'s motion. ``name(s)``: how a
    slice is named to the user. Returns the :class:`PlaneCheck` and the pairs' filter ``keep(s, idx) -> bool mask``.
    """
    x = model.positions_mm if positions_mm is None else np.asarray(positions_mm, dtype=np.float64)
    organ_of = np.asarray(model.organs)[model.organ_index]
    planes = _Planes(model, slices, planning_volume, captured_volume, labels, geometry, label_values, centre_mm, name, **capture)
    pairs = []
    for s in slices:
        on = model.slice_mask(s.orientation, s.index)
        for o in model.organs:
            if np.any(on & (organ_of == o)):
                pairs.append((s, o))
    out = PlaneCheck()
    every = np.arange(model.n)
    motion = {}
    for s, o in pairs:
        sel = every[organ_of == o]
        d = (moved(s, sel) - x[sel]) @ plane_projector(model, s.orientation).T
        motion[(s, o)] = d.mean(axis=0)
        size = float(np.linalg.norm(d, axis=1).mean())
        if size > MAX_MOTION_MM:
            out.reasons[(s, o)] = f"its registered motion averages {size:.1f} mm, more than a frame shows ({MAX_MOTION_MM:g} mm)"
    # planes that disagree on the motion they share (superior-inferior for sagittal and coronal)
    for o in model.organs:
        seen = [(s, motion[(s, o)]) for s in slices if (s, o) in motion]
        for i in range(len(seen)):
            for j in range(i + 1, len(seen)):
                (s1, m1), (s2, m2) = seen[i], seen[j]
                shared = plane_projector(model, s1.orientation) @ plane_projector(model, s2.orientation)
                diff = float(np.linalg.norm(shared @ (m1 - m2)))
                if diff > DISAGREE_MM:
                    out.disagreements.append({"organ": o, "planes": [name(s1), name(s2)], "difference_mm": round(diff, 2)})
    kept = [p for p in pairs if p not in out.reasons]
    out.match_none = planes.match(None)
    out.match_all = planes.match(_combined(model, x, slices, moved, pairs)) if pairs else out.match_none
    current = planes.match(_combined(model, x, slices, moved, kept)) if kept else out.match_none
    while len(kept) > 1:
        trials = [(planes.match(_combined(model, x, slices, moved, [q for q in kept if q != p])), p) for p in kept]
        best, p = max(trials, key=lambda t: t[0])
        if best <= current + MIN_GAIN:
            break
        out.reasons[p] = (f"the planes match the image better without it (mean correlation {current:.3f} with it, "
                          f"{best:.3f} without)")
        kept.remove(p)
        current = best
    if kept and out.match_none > current + MIN_GAIN:
        for p in kept:
            out.reasons[p] = (f"its motion matches the planes worse than no motion (mean correlation {current:.3f} against "
                              f"{out.match_none:.3f} unmoved)")
        kept = []
        current = out.match_none
    out.kept = [(name(s), o) for s, o in kept]
    out.dropped = [(name(s), o) for s, o in pairs if (s, o) not in kept]
    out.reasons = {(name(s), o): r for (s, o), r in out.reasons.items()}
    out.match_kept = current
    out.evaluations = planes.evaluations
    if warn:
        for (p, o), r in out.reasons.items():
            warnings.warn(f"plane check: {p}, {o}: not driven: {r}", InputWarning, stacklevel=2)
        for d in out.disagreements:
            warnings.warn(f"plane check: {d['planes'][0]} and {d['planes'][1]} disagree on the {d['organ']}'s shared motion by "
                          f"{d['difference_mm']:.1f} mm", InputWarning, stacklevel=2)
    keep_set = set(kept)

    def keep(s, idx):
        return np.array([(s, o) in keep_set for o in organ_of[idx]], dtype=bool)

    return out, keep
