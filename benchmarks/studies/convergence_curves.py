"""Study (2026-11-22; answer in benchmarks/studies/README.md). Pancreas error against step with no stopping rule, for Courant numbers and damping factors.

The evidence behind the solver's defaults (CFL 0.5, damping factor 4): at the old damping the slowest
mode of the scene stays under-damped and the error swings long after the residual has settled; more
damping removes the swing, and a larger time step reaches the plateau in fewer steps.

    python benchmarks/studies/convergence_curves.py --out benchmarks/studies/results/damping.png
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np


from warpmpm.experiment import raw_numbers as raw

import warp as wp

from warpmpm.driving import ConvergenceConfig, SliceDrivenEstimator
from warpmpm.slices import InPlaneAffine
from warpmpm.targets import affine_targets
from warpmpm.groundtruth import paper_affine, paper_ground_truth
from warpmpm.experiment import CaseConfig, prepare_case
from warpmpm.solvers import ExplicitConfig, SolverConfig

SETTINGS = [(0.3, 1.0), (0.3, 2.0), (0.3, 4.0), (0.3, 8.0), (0.5, 4.0)]  # (CFL, damping factor)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--deformations", default="1,8")
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--every", type=int, default=50)
    p.add_argument("--out", default="benchmarks/studies/results/damping.png")
    a = p.parse_args(argv)
    wp.config.log_level = wp.LOG_ERROR  # no init banner or module-load lines
    prep = prepare_case(CaseConfig(particle_step=2, device="cpu"))
    model = prep.full_model
    sl = prep.resolve_slices(model, None)
    pan = model.organ_slice("pancreas")
    curves = {}
    for d in [int(x) for x in a.deformations.split(",")]:
        gt = paper_ground_truth(model, d, centre_mm=prep.centre_mm, device="cpu")
        _, tg = affine_targets(model, model.positions_mm, sl, [InPlaneAffine(paper_affine(d))], prep.centre_mm)
        for cfl, factor in SETTINGS:
            pts = []

            def cb(est, step, rel, rms):
                if step % a.every == 0:
                    pts.append((step, float(np.linalg.norm(est.positions_mm()[pan] - gt.positions_mm[pan], axis=1).mean())))

            est = SliceDrivenEstimator(model, sl, solver_config=SolverConfig(device="cpu", explicit=ExplicitConfig(cfl=cfl, damping_factor=factor)),
                                       convergence=ConvergenceConfig(max_steps=a.steps, th_s=10**9),
                                       extra_points_mm=np.vstack([tg, gt.positions_mm]), callback=cb)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "did not converge": no stopping rule here, by design
                est.estimate(tg)
            curves[(d, cfl, factor)] = pts
            print(f"deformation {d}, CFL {cfl}, damping x{factor:g}: " + " ".join(f"{s}:{e:.2f}" for s, e in pts), flush=True)
    raw.save(__file__, [{"deformation": d, "cfl": c, "damping_factor": f, "step_error_mm": pts}
                                    for (d, c, f), pts in curves.items()])
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    defs = sorted({k[0] for k in curves})
    fig, axs = plt.subplots(1, len(defs), figsize=(5 * len(defs), 3.8), sharey=True, squeeze=False)
    for ax, d in zip(axs[0], defs):
        for cfl, factor in SETTINGS:
            s, e = zip(*curves[(d, cfl, factor)])
            ax.plot(s, e, label=f"CFL {cfl}, damping x{factor:g}", lw=2 if (cfl, factor) in [(0.5, 4.0), (0.3, 1.0)] else 1)
        ax.set_title(f"phantom seed 0, psdl, deformation {d}")
        ax.set_xlabel("step (no stopping rule)")
        ax.grid(alpha=0.3)
    axs[0][0].set_ylabel("mean pancreas error (mm)")
    axs[0][-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
