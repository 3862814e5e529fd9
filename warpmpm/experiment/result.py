"""What a run returns: :class:`Scores` per method and the whole :class:`RunResult`, each with ``to_json()``.

The JSON written by ``warpmpm run --json`` is ``RunResult.to_json()``; its keys are a contract (keys
may be added, none removed or renamed).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

__all__ = ["Scores", "EstimateScores", "RunResult"]


@dataclass(kw_only=True)
class Scores:
    """Accuracy of one method on the pancreas against the GT (:func:`warpmpm.metrics.evaluate`).

    Attributes:
        error_mm: mean particle distance to the GT (mm); p95_mm, max_mm: its 95th percentile and maximum.
        dice: Dice of the voxelised pancreas regions. n: particles scored.
        error_offslice_mm: mean error of the pancreas particles that no driving slice holds (what the
            estimate inferred, not what it was told), whatever ``excluded_driven`` says.
        info: method-specific values (a baseline's time, whether it fell back to the identity...).
        organs: organ -> its scores (:func:`warpmpm.experiment.organs.organ_scores`: error, p95, on/off-plane split,
            LR/AP/SI errors, distance to the pancreas for the organs at risk); written as ``organs`` in the JSON.
    """

    error_mm: float
    p95_mm: float
    max_mm: float
    dice: float
    n: int
    error_offslice_mm: float = float("nan")
    info: dict = field(default_factory=dict)
    organs: dict = field(default_factory=dict)

    @classmethod
    def of(cls, metrics: dict, error_offslice_mm: float = float("nan"), **info) -> "Scores":
        return cls(**{k: metrics[k] for k in ("error_mm", "p95_mm", "max_mm", "dice", "n")}, error_offslice_mm=error_offslice_mm,
                   info=dict(info))

    def to_json(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("info", "organs")}
        return d | self.info | ({"organs": self.organs} if self.organs else {})


@dataclass(kw_only=True)
class EstimateScores(Scores):
    """The estimate's scores and how it ran.

    Attributes (beside :class:`Scores`'): steps run; wall_s of the drive loop; converged and reason
    (the stopping rule that ended it: threshold, stagnation, stalled, max_steps); rms_residual_mm and
    rel_residual of the driven particles at the end; ms_per_step; settled and body_motion_mm (whether
    the whole model had stopped moving: the 99th-percentile particle displacement over the last 100
    steps); min_det_f (the smallest particle volume ratio: near 0, an element collapsed). With the quasi-static
    solver (``solver.method`` in the run's JSON) steps are Newton iterations, linear_iterations their
    conjugate-gradient iterations, body_motion_mm the last iteration's largest particle move and reason
    ``settled`` or ``max_iterations``. ``finished_by``: which solver ended the frame (``explicit``,
    ``quasistatic``, or ``quasistatic+explicit`` when ``method="auto"`` went on explicitly; then steps are the
    explicit steps and linear_iterations those of the quasi-static iterations before them).
    """

    steps: int
    wall_s: float
    converged: bool
    """The whole model settled and the driven particles met the stopping rule (whatever the solver)."""
    reason: str
    rms_residual_mm: float
    rel_residual: float
    ms_per_step: float
    settled: bool = False
    body_motion_mm: float = float("nan")
    min_det_f: float = float("nan")
    linear_iterations: int = 0
    finished_by: str = "explicit"
    slice_converged: bool | None = None
    """The driven particles met the stopping rule (``reason``), whether or not the rest of the model had settled."""
    plane_match: float = float("nan")
    """Registration targets: the mean correlation of the captured planes with the planning image moved to the estimate
    (:mod:`warpmpm.plane_check`); ``plane_match_unmoved``: the same for no motion."""
    plane_match_unmoved: float = float("nan")
    flag: str = ""
    """Non-empty when the estimate is worse than no motion by its own measure (or nothing could be driven)."""


@dataclass(kw_only=True)
class RunResult:
    """One run: what was run, the estimate and every baseline. ``to_json()`` is the ``--json`` file.

    Attributes:
        case, organs (letters), slices (input-volume labels), protocol, deformation, targets, device.
        n_particles: per organ. n_driven: driven particles. excluded_driven: whether they were left out
        of the metrics. solver: the estimator's grid, time step and damping. gains: the PID gains in
        physical units. gt: the GT's parameters, steps and time. results: method -> :class:`Scores`.
        registration: the slice registration's own error and time (the registration target kinds).
        drive: ``inplane``, ``pinned`` or ``3d`` (GT targets). target_in_plane_error_mm: in-plane distance
        of the slices' pancreas targets to their true positions.
        positions_mm: the estimate's final particle positions (N, 3), not written to JSON. solver, gains, device: the
        slice-driven MPM's (empty when it did not run).
        total_wall_s, selection: filled by :func:`run_case` and the CLI.
    """

    case: str
    organs: str
    slices: list[str]
    protocol: str
    deformation: int
    targets: str
    device: str
    n_particles: dict
    n_driven: int
    excluded_driven: bool
    solver: dict
    gains: dict
    gt: dict
    results: dict[str, Scores]
    registration: dict | None = None
    positions_mm: np.ndarray | None = field(default=None, repr=False)
    drive: str = "pinned"
    target_in_plane_error_mm: float = float("nan")
    total_wall_s: float | None = None
    selection: dict | None = None
    estimator: str = "slice-driven"
    """Which estimator ``results["estimate"]`` is (:attr:`~warpmpm.experiment.config.CaseConfig.estimator`); each
    estimator run is also under its own name (``copy``, ``slice-driven``)."""

    @property
    def estimate(self) -> EstimateScores:
        return self.results["estimate"]  # type: ignore[return-value]

    def to_json(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in fields(self)
               if f.name not in ("results", "registration", "positions_mm", "total_wall_s", "selection")}
        out["results"] = {k: v.to_json() for k, v in self.results.items()}
        if self.registration is not None:
            out["results"]["registration"] = dict(self.registration)
        if self.total_wall_s is not None:
            out["total_wall_s"] = self.total_wall_s
        if self.selection is not None:
            out["selection"] = self.selection
        return out

