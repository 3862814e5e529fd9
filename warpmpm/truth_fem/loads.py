"""The loads and boundary conditions of a truth frame: breathing cycles at the diaphragm, drift, stomach filling,
the duodenal push and peristalsis, as eigenstrains and prescribed displacements."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ..anatomy import TISSUE_CODE as _T
from ..errors import InputError
from ..images import Geometry
from .config import TruthConfig
from .mesh import BoxMesh

__all__ = ["anatomical_axes", "BreathingCycles", "draw_loads", "cell_eigenstrain", "load_state",
           "diaphragm_displacement"]


def anatomical_axes(geometry: Geometry) -> dict:
    """The scan axis (0, 1, 2 = i, j, k) and sign of posterior (+y) and superior (+z) in world LPS."""
    D = geometry.direction_matrix
    out = {}
    for name, row in (("lateral", 0), ("posterior", 1), ("superior", 2)):
        ax = int(np.argmax(np.abs(D[row])))
        out[name] = (ax, float(np.sign(D[row, ax])))
    if len({v[0] for v in out.values()}) < 3:
        raise InputError(f"the scan's axes are too oblique to find its posterior and superior faces (direction {geometry.direction})")
    return out


@dataclass
class BreathingCycles:
    """Per-cycle breathing parameters (drawn once per series)."""

    period_s: list
    si_mm: list
    ap_mm: list
    baseline_mm: list

    @classmethod
    def draw(cls, rng, duration_s: float) -> "BreathingCycles":
        p, si, ap, base, t = [], [], [], [], 0.0
        while t <= duration_s + 5.0 or len(p) < 2:
            p.append(float(rng.uniform(3.5, 5.0)))
            si.append(float(rng.uniform(8.0, 20.0)))
            ap.append(float(rng.uniform(2.0, 5.0)))
            base.append(0.0 if not base else float(rng.uniform(-1.5, 1.5)))
            t += p[-1]
        return cls(p, si, ap, base)

    def at(self, t: float) -> tuple[float, float]:
        """(inferior mm, anterior mm) of the diaphragm side at time ``t`` (s)."""
        start = 0.0
        for c, T in enumerate(self.period_s):
            if t < start + T or c == len(self.period_s) - 1:
                u = (t - start) / T
                w = math.sin(math.pi * min(u, 1.0)) ** 4
                nxt = self.baseline_mm[c + 1] if c + 1 < len(self.baseline_mm) else self.baseline_mm[c]
                base = self.baseline_mm[c] + (nxt - self.baseline_mm[c]) * min(u, 1.0)
                return self.si_mm[c] * w + base, self.ap_mm[c] * w
            start += T
        return 0.0, 0.0


def _principal_axis(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    return c, vt[0]


def draw_loads(mesh: BoxMesh, cfg: TruthConfig) -> dict:
    """The parameters of every load of ``cfg.loads`` for this mesh, drawn from ``cfg.seed``."""
    rng = np.random.default_rng([cfg.seed, 202])
    duration = max(cfg.frames - 1, 1) / cfg.fps
    out: dict = {}
    if "breathing" in cfg.loads:
        out["breathing"] = asdict(BreathingCycles.draw(rng, duration))
    if "drift" in cfg.loads:
        out["drift"] = {"rate_mm_s": float(rng.uniform(0.05, 0.2))}
    if "filling" in cfg.loads:
        out["filling"] = {"volume_gain": float(rng.uniform(0.05, 0.15)), "duration_s": duration}
    pts = mesh.sample_local_mm().reshape(-1, 3)
    pt = mesh.point_tissue.ravel()
    if "push" in cfg.loads:
        organ = "duodenum" if np.any(pt == _T["duodenum"]) else "stomach"
        pan = pts[pt == _T["pancreas"]]
        nb = pts[pt == _T[organ]]
        if len(nb) == 0:
            raise InputError("the push load needs a duodenum or a stomach in the label map")
        # the neighbour's points closest to the pancreas: their centroid is the bolus's centre
        from scipy.spatial import cKDTree

        d, _ = cKDTree(pan[:: max(1, len(pan) // 20000)]).query(nb)
        centre = nb[d <= np.percentile(d, 5)].mean(0)
        out["push"] = {"organ": organ, "centre_mm": mesh.local_to_world(centre[None])[0].tolist(),
                       "radius_mm": float(rng.uniform(12.0, 20.0)), "eigenstrain": float(rng.uniform(0.3, 0.6)) / 3.0,
                       "duration_s": duration}
    if "peristalsis" in cfg.loads:
        duo = pts[pt == _T["duodenum"]]
        if len(duo) == 0:
            raise InputError("the peristalsis load needs a duodenum in the label map")
        c, axis = _principal_axis(duo)
        s = (duo - c) @ axis
        out["peristalsis"] = {"centre_mm": mesh.local_to_world(c[None])[0].tolist(), "axis": (mesh.geometry.direction_matrix @ axis).tolist(),
                              "start_mm": float(s.min()), "speed_mm_s": float(rng.uniform(5.0, 15.0)),
                              "width_mm": 12.0, "eigenstrain": -float(rng.uniform(0.05, 0.10)) / 3.0}
    return out


def cell_eigenstrain(mesh: BoxMesh, loads: dict, t: float) -> np.ndarray:
    """(n_cells,) isotropic eigenstrain of every cell at time ``t`` (the mean over its sample points)."""
    shape = mesh.keep.shape
    e = np.zeros(int(np.prod(shape)))
    pt = mesh.point_tissue
    if "filling" in loads:
        L = loads["filling"]
        ramp = min(t / L["duration_s"], 1.0) if L["duration_s"] > 0 else 1.0
        e += (np.cbrt(1.0 + L["volume_gain"] * ramp) - 1.0) * mesh.fractions["stomach"].ravel()
    if "push" in loads or "peristalsis" in loads:
        pts = mesh.sample_local_mm()
        if "push" in loads:
            L = loads["push"]
            c = mesh.world_to_local(np.asarray(L["centre_mm"])[None])[0]
            amp = L["eigenstrain"] * (math.sin(math.pi * min(t / L["duration_s"], 1.0)) ** 2 if L["duration_s"] > 0 else 1.0)
            w = np.exp(-0.5 * np.sum((pts - c) ** 2, -1) / L["radius_mm"] ** 2) * (pt == _T[L["organ"]])
            e += amp * w.mean(1)
        if "peristalsis" in loads:
            L = loads["peristalsis"]
            c = mesh.world_to_local(np.asarray(L["centre_mm"])[None])[0]
            axis = mesh.geometry.direction_matrix.T @ np.asarray(L["axis"])
            s = (pts - c) @ axis
            pos = L["start_mm"] + L["speed_mm_s"] * t
            w = np.exp(-0.5 * ((s - pos) / L["width_mm"]) ** 2) * (pt == _T["duodenum"])
            e += L["eigenstrain"] * min(t / 0.5, 1.0) * w.mean(1)  # the band forms over the first 0.5 s
    return e.reshape(shape)


def load_state(loads: dict, t: float) -> dict:
    """What each aperiodic load amounts to at time ``t`` (for a frame's record): the stomach's volume gain, the push's
    eigenstrain at its centre, the peristaltic band's position along the duodenum's axis (mm from its start)."""
    out = {}
    if "filling" in loads:
        L = loads["filling"]
        out["filling_volume_gain"] = L["volume_gain"] * (min(t / L["duration_s"], 1.0) if L["duration_s"] > 0 else 1.0)
    if "push" in loads:
        L = loads["push"]
        out["push_eigenstrain"] = L["eigenstrain"] * (math.sin(math.pi * min(t / L["duration_s"], 1.0)) ** 2 if L["duration_s"] > 0 else 1.0)
    if "peristalsis" in loads:
        L = loads["peristalsis"]
        out["peristalsis_band_mm"] = L["speed_mm_s"] * t
    if "drift" in loads:
        out["drift_mm"] = loads["drift"]["rate_mm_s"] * t
    return out


def diaphragm_displacement(loads: dict, t: float) -> tuple[float, float]:
    """(inferior, anterior) displacement (mm) of the diaphragm side at time ``t``: breathing plus drift."""
    inf, ant = 0.0, 0.0
    if "breathing" in loads:
        b = BreathingCycles(**loads["breathing"])
        inf, ant = b.at(t)
    if "drift" in loads:
        inf += loads["drift"]["rate_mm_s"] * t
    return inf, ant
