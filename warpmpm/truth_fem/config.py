"""What a finite-element truth series is made of: the loads it can combine and :class:`TruthConfig`."""

from __future__ import annotations

import math
from dataclasses import dataclass


from ..errors import InputError

__all__ = ["LOADS", "DIRECT_MAX_DOFS", "TruthConfig"]


#: The loads a truth frame can combine.
LOADS = ("breathing", "drift", "filling", "push", "peristalsis")

#: Free unknowns above which the equilibrium is solved by AMG-preconditioned conjugate gradients (below: SuperLU;
#: measured on the MR sample, 71k unknowns: SuperLU 60 s to factorise, AMG-CG 1.2-1.5 s a frame, 23 iterations).
DIRECT_MAX_DOFS = 20_000


@dataclass(frozen=True)
class TruthConfig:
    """How a finite-element truth series is made (:func:`make_truth`)."""

    loads: tuple[str, ...] = ("breathing",)
    """Loads of every frame, from :data:`LOADS`; ``breathing`` alone is free breathing."""
    frames: int = 16
    """Number of frames; frame ``n`` is at ``n / fps`` seconds."""
    fps: float = 4.0
    """Frames per second (a cine frame every 0.1-0.3 s on an MR-Linac)."""
    seed: int = 0
    """Seeds the materials, the breathing cycles and the aperiodic loads."""
    cell_mm: float = 5.0
    """Edge of the hexahedral cells (mm); mesh convergence h against h/2 is in ``benchmarks/fem_truth.py``."""
    margin_mm: float = 30.0
    """Tissue meshed around the organs' bounding box (mm, each side; clipped to the scan)."""
    interface_mm: float = 3.0
    """Thickness of the sliding layer between two organs (mm); 0: organs bonded to each other."""
    interface_ratio: float | None = None
    """Shear modulus of the sliding layer over the softer neighbour's; None: drawn in 0.02-0.1."""
    posterior_taper_mm: float = 40.0
    """Distance from the held back over which the diaphragm side's motion grows from zero to full (mm)."""
    sample_mm: float = 1.5
    """Spacing of the points that give a cell its tissue (mm)."""
    rtol: float = 1e-8
    """Relative residual the iterative solver stops at."""

    def __post_init__(self):
        bad = [x for x in self.loads if x not in LOADS]
        if bad or not self.loads:
            raise InputError(f"unknown load(s) {bad or '(none)'}; choose from {', '.join(LOADS)}, comma-separated")
        if "breathing" not in self.loads and "drift" not in self.loads and not set(self.loads) & {"filling", "push", "peristalsis"}:
            raise InputError("a truth needs at least one load")
        if not (isinstance(self.frames, int) and not isinstance(self.frames, bool) and 1 <= self.frames <= 10_000):
            raise InputError(f"--frames must be a whole number in 1..10000, got {self.frames!r}")
        for name, lo, hi in (("fps", 0.1, 100.0), ("cell_mm", 0.5, 50.0), ("margin_mm", 0.0, 200.0), ("interface_mm", 0.0, 20.0),
                             ("posterior_taper_mm", 0.0, 500.0), ("sample_mm", 0.2, 10.0)):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise InputError(f"--{name.replace('_', '-')} must be a finite number in {lo}..{hi}, got {v!r}")
        if self.interface_ratio is not None and not (0 < self.interface_ratio <= 1):
            raise InputError(f"interface ratio must be in (0, 1], got {self.interface_ratio!r}")
        if not (isinstance(self.seed, int) and 0 <= self.seed < 2**31):
            raise InputError(f"--seed must be a whole number in 0..{2**31 - 1}, got {self.seed!r}")
