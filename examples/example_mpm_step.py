"""The MPM solver on its own: a soft block (pancreas) pressed against a stiff one (duodenum).

    python examples/example_mpm_step.py --steps 2000

The pattern of the solver (as Newton's): an ``MPMModel`` built once from a particle model (materials,
mass, grid, time step), two ``State`` objects that change, and ``solver.step(state_in, state_out,
control)`` with the control a per-particle force in newtons. Here the soft block's far face is pushed
toward the stiff block. With no damping the momentum of the scene equals the impulse of the force
(checked in ``render``); the stiff block barely deforms (the ~3000x stiffness contrast) and is set
moving through the shared grid alone (contact comes free).
"""

import argparse


import numpy as np
import warp as wp

from warpmpm.scenes import block_model, merge_models
from warpmpm.solvers import ExplicitConfig, MPMModel, MPMSolver, SolverConfig


class Example:
    def __init__(self, voxels=6, push_m_s2=2.0e4, device="cpu"):
        soft = block_model((voxels,) * 3, (2.0, 2.0, 2.0), "pancreas")
        stiff = block_model((voxels,) * 3, (2.0, 2.0, 2.0), "duodenum", origin_mm=(2.0 * voxels, 0.0, 0.0))
        self.particles = merge_models(soft, stiff)
        # no grid damping, so that momentum = impulse holds exactly (the estimator damps toward rest)
        self.model = MPMModel(self.particles, SolverConfig(device=device, explicit=ExplicitConfig(damping_per_s=0.0)))
        self.solver = MPMSolver(self.model)
        self.state_0, self.state_1 = self.model.state(), self.model.state()
        # a constant force on the soft block's far (x = 0) face, toward the stiff block (N)
        x = self.particles.positions_mm
        face = x[:, 0] < x[:, 0].min() + 1.0
        force = np.zeros((self.particles.n, 3), dtype=np.float32)
        force[face, 0] = self.model.mass_kg[face] * push_m_s2
        self.total_force_n = force.sum(0).astype(np.float64)
        self.control = wp.array(force, dtype=wp.vec3, device=self.model.device)
        self.soft = self.particles.organ_slice("pancreas")
        self.steps = 0

    def step(self):
        self.solver.step(self.state_0, self.state_1, self.control)
        self.state_0, self.state_1 = self.state_1, self.state_0
        self.steps += 1

    def momentum(self) -> np.ndarray:
        """Total momentum of the particles (kg m/s)."""
        return (self.model.mass_kg[:, None] * self.state_0.v.numpy()).sum(0)

    def impulse(self) -> np.ndarray:
        """Impulse of the applied force so far (N s)."""
        return self.total_force_n * self.steps * self.model.dt_s

    def displacement_mm(self) -> np.ndarray:
        return self.state_0.positions_mm() - self.particles.positions_mm

    def render(self):
        d = self.displacement_mm()
        p, j = self.momentum(), self.impulse()
        print(f"step {self.steps}: soft block moved {d[self.soft, 0].mean():.3f} mm along x, stiff block "
              f"{d[~self.soft, 0].mean():.4f} mm; momentum {p[0]:.3e} kg m/s vs impulse {j[0]:.3e} N s "
              f"(dt {self.model.dt_s:.2e} s, dx {self.model.dx_mm:.2f} mm)")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--voxels", type=int, default=6, help="block edge in voxels of 2 mm")
    p.add_argument("--device", default="cpu")
    a = p.parse_args(argv)
    wp.config.log_level = wp.LOG_ERROR
    with wp.ScopedDevice(a.device):
        ex = Example(a.voxels, device=a.device)
        for i in range(a.steps):
            ex.step()
            if (i + 1) % max(1, a.steps // 4) == 0:
                ex.render()
    return ex


if __name__ == "__main__":
    main()
