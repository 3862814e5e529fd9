"""The drive of the explicit relaxation: the PID force that pulls the driven particles toward their targets.

PID force (per driven particle i, acceleration form, physical units)::

    e_i = x_i^target - x_i                       (m)
    a_i = Kp e_i - Kd v_i + Ki sum(e_i dt)       (m/s^2;  Kp in 1/s^2, Kd in 1/s, Ki in 1/s^3)
    f_i = m_i clamp(a_i, max_accel)              (N)

Anti-windup: the integral stops growing while the command is clamped, and its own action never exceeds
the clamp. Without it, the part of the error the grid cannot remove (driven particles closer than a cell
pulled apart) was integrated for as long as the frame ran, up to 21x the clamp in 3,000 steps.

Writing the force as mass times a controlled acceleration makes one set of gains work for the
soft pancreas and the stiff duodenum alike (their masses differ by ~1500x under mass scaling).
``-Kd v`` is the derivative of the error for a target at rest, without the kick a finite
difference gives when the target jumps. The default gains derive from the solver's time step
(``omega = omega_dt / dt``, ``Kp = omega^2``, ``Kd = 2 zeta omega``, ``Ki = ki_ratio omega^3``) so
they stay stable for any scene, and are reported in physical units in every result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import warp as wp

from ..errors import InputError

__all__ = ["Gains", "DriveConfig", "pid_force"]

# forward kernels only, no adjoints to compile (why: warpmpm.solvers.explicit_kernels)
wp.set_module_options({"enable_backward": False})


@dataclass(frozen=True)
class Gains:
    """Resolved PID gains in physical units (acceleration form, see module docstring)."""

    kp_per_s2: float
    """Proportional gain (1/s^2)."""
    kd_per_s: float
    """Derivative (velocity) gain (1/s)."""
    ki_per_s3: float
    """Integral gain (1/s^3)."""
    max_accel_m_s2: float
    """Clamp of the commanded acceleration magnitude (m/s^2)."""

    def to_json(self) -> dict:
        return {"kp_per_s2": self.kp_per_s2, "kd_per_s": self.kd_per_s, "ki_per_s3": self.ki_per_s3,
                "max_accel_m_s2": self.max_accel_m_s2}


@dataclass(frozen=True)
class DriveConfig:
    """PID gains (acceleration form, see module docstring) and clamp.

    Attributes:
        kp_per_s2, kd_per_s, ki_per_s3: explicit gains; None derives them from the time step.
        omega_dt: drive frequency times the time step for the derived gains (stability needs << 1).
        zeta: damping ratio of the derived derivative gain.
        ki_ratio: derived ``Ki = ki_ratio * omega^3``; None: 0.02 for a frame that stops on the driven slice,
            0 (a PD drive) for one that waits for the body to settle. The integral pushes every driven particle
            exactly onto its target, which the grid can give a single particle layer only by stretching the
            layers beside it (they share its grid nodes): against the FEM, the settled error of a scaled slice
            is 17 % with the integral and 9 % without, and with it the body creeps for as long as it runs
            (17 -> 20 % by 6,000 steps; without it 9.3 % from step 400 to 6,000). Stopping on the slice, the
            integral gets the slice to its targets sooner (phantom, paper protocol 3.0 against 3.2 mm).
        max_accel_m_s2: clamp of the commanded acceleration magnitude; None: ``0.05 * dx / dt^2``
            (at most 5% of a cell per step squared).
    """

    kp_per_s2: float | None = None
    kd_per_s: float | None = None
    ki_per_s3: float | None = None
    omega_dt: float = 0.3
    zeta: float = 1.0
    ki_ratio: float | None = None
    max_accel_m_s2: float | None = None

    def resolve(self, dt_s: float, dx_mm: float, settle: bool = False) -> Gains:
        """Gains in physical units for the time step and cell; ``settle``: the frame waits for the body."""
        for name in ("kp_per_s2", "kd_per_s", "ki_per_s3", "max_accel_m_s2"):
            value = getattr(self, name)
            if value is not None and (not math.isfinite(value) or value < 0):
                raise InputError(f"driving gain {name} must be a finite number >= 0, got {value}")
        ki_ratio = (0.0 if settle else 0.02) if self.ki_ratio is None else self.ki_ratio
        if not (0 < self.omega_dt < 1) or self.zeta < 0 or not (math.isfinite(ki_ratio) and ki_ratio >= 0):
            raise InputError("drive omega_dt must be in (0, 1); zeta and ki_ratio must be >= 0")
        w = self.omega_dt / dt_s
        kp = w * w if self.kp_per_s2 is None else self.kp_per_s2
        kd = 2 * self.zeta * w if self.kd_per_s is None else self.kd_per_s
        ki = ki_ratio * w**3 if self.ki_per_s3 is None else self.ki_per_s3
        amax = 0.05 * dx_mm * 1e-3 / dt_s**2 if self.max_accel_m_s2 is None else self.max_accel_m_s2
        if kp * dt_s * dt_s > 0.25 or kd * dt_s > 1.0:
            raise InputError(
                f"driving gains too large for the time step {dt_s:.3e} s: need Kp dt^2 <= 0.25 and Kd dt <= 1 "
                f"(Kp <= {0.25 / dt_s**2:.3e} 1/s^2, Kd <= {1 / dt_s:.3e} 1/s)"
            )
        return Gains(kp, kd, ki, amax)


@wp.kernel
def pid_force(
    driven: wp.array(dtype=int),
    target: wp.array(dtype=wp.vec3),
    axes: wp.array(dtype=wp.mat33),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    integral: wp.array(dtype=wp.vec3),
    bias: wp.array(dtype=wp.vec3),
    centre: wp.vec3,
    kp: float,
    kd: float,
    ki: float,
    max_accel: float,
    dt: float,
    f_ext: wp.array(dtype=wp.vec3),
    sums: wp.array(dtype=float, ndim=2),
    row: int,
):
    """PID force on driven particle ``driven[j]`` toward ``target[j]`` along the directions ``axes[j]`` drives
    (a projector: the identity pins all three components, a slice plane's projector only the in-plane
    ones); accumulates the residual sums ``sums[row] = [sum |e|^2, sum |target - centre|^2]`` over the
    driven directions (one row per step, read back in batches)."""
    j = wp.tid()
    p = driven[j]
    P = axes[j]
    e = P * (target[j] - x[p])
    acc_i = integral[j] + e * dt
    # anti-windup: the integral action alone never exceeds the clamp
    if ki > 0.0 and wp.length(ki * acc_i) > max_accel:
        acc_i = acc_i * (max_accel / (ki * wp.length(acc_i)))
    a = P * (bias[j] + kp * e - kd * v[p] + ki * acc_i)  # nothing along the directions this frame does not drive
    n = wp.length(a)
    if n > max_accel:
        a = a * (max_accel / n)
        acc_i = integral[j]  # anti-windup: no integration while the command is saturated
    integral[j] = acc_i
    f_ext[p] = mass[p] * a
    r = P * (target[j] - centre)
    wp.atomic_add(sums, row, 0, wp.dot(e, e))
    wp.atomic_add(sums, row, 1, wp.dot(r, r))
