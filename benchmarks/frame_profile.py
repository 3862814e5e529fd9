"""Where the time of one frame goes: kernels, residual read-backs and convergence checks, Python.

Runs one frame (phantom by default, organs ``psdl``, mid-pancreas axial slice, paper deformation 1)
with the default settings and times every ``wp.launch`` by kernel, every residual read-back
(``wp.array.numpy``) and the rest (the Python of the drive loop and the stopping rule). On the CPU
Warp runs a launch to completion before returning, so a launch's wall time is its kernel's time plus
the launch overhead; the overhead is measured separately with an empty kernel. On CUDA, launches are
asynchronous: the table then shows launch (enqueue) times and the read-backs absorb the kernel time.

    python benchmarks/frame_profile.py                  # default phantom, particle step 2
    python benchmarks/frame_profile.py --particle-step 1
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import numpy as np


from warpmpm.experiment import raw_numbers as raw

import warp as wp

from warpmpm.driving import SliceDrivenEstimator
from warpmpm.slices import InPlaneAffine
from warpmpm.targets import affine_targets
from warpmpm.groundtruth import paper_affine
from warpmpm.experiment import CaseConfig, prepare_case


@wp.kernel
def _empty(a: wp.array(dtype=float)):
    pass


def launch_overhead_us(device: str, n: int = 2000) -> float:
    a = wp.zeros(1, dtype=float, device=device)
    wp.launch(_empty, 1, [a], device=device)
    wp.synchronize_device(device)
    t = time.perf_counter()
    for _ in range(n):
        wp.launch(_empty, 1, [a], device=device)
    wp.synchronize_device(device)
    return (time.perf_counter() - t) / n * 1e6


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--particle-step", type=int, default=2)
    p.add_argument("--deformation", type=int, default=1)
    p.add_argument("--device", default=None)
    p.add_argument("--phantom-resolution", type=float, default=1.0, help="phantom voxel size factor (3: the selection sweep's)")
    a = p.parse_args(argv)
    wp.config.log_level = wp.LOG_ERROR  # no init banner or module-load lines
    wp.init()
    device = a.device or ("cuda" if wp.is_cuda_available() else "cpu")
    prep = prepare_case(CaseConfig(particle_step=a.particle_step, device=device, phantom_resolution=a.phantom_resolution))
    model = prep.full_model
    sl = prep.resolve_slices(model, None)
    _, tg = affine_targets(model, model.positions_mm, sl, [InPlaneAffine(paper_affine(a.deformation))], prep.centre_mm)
    est = SliceDrivenEstimator(model, sl, extra_points_mm=tg)
    est.estimate(tg)  # warm-up: compile and load kernels
    est = SliceDrivenEstimator(model, sl, extra_points_mm=tg)

    times: dict[str, float] = defaultdict(float)
    counts: dict[str, int] = defaultdict(int)
    real_launch, real_numpy = wp.launch, wp.array.numpy

    def timed_launch(kernel, *args, **kwargs):
        t = time.perf_counter()
        out = real_launch(kernel, *args, **kwargs)
        times[kernel.key] += time.perf_counter() - t
        counts[kernel.key] += 1
        return out

    def timed_numpy(self):
        t = time.perf_counter()
        out = real_numpy(self)
        times["read-backs (.numpy)"] += time.perf_counter() - t
        counts["read-backs (.numpy)"] += 1
        return out

    wp.launch, wp.array.numpy = timed_launch, timed_numpy
    try:
        t0 = time.perf_counter()
        res = est.estimate(tg)
        wall = time.perf_counter() - t0
    finally:
        wp.launch, wp.array.numpy = real_launch, real_numpy
    overhead = launch_overhead_us(device)
    n_launch = sum(c for k, c in counts.items() if not k.startswith("read"))
    print(f"device {device}, {model.n} particles, grid {est.mpm.grid_shape} ({np.prod(est.mpm.grid_shape):,} nodes, "
          f"dx {est.mpm.dx_mm:.2f} mm), {res.steps} steps, {res.reason}, frame {wall:.2f} s ({wall / res.steps * 1e3:.2f} ms/step)\n")
    print("| part | calls | total s | ms per step | share |")
    print("|---|---|---|---|---|")
    for k in sorted(times, key=times.get, reverse=True):
        print(f"| {k} | {counts[k]} | {times[k]:.3f} | {times[k] / res.steps * 1e3:.3f} | {times[k] / wall:.1%} |")
    rest = wall - sum(times.values())
    print(f"| Python: drive loop, stopping rule, bookkeeping | | {rest:.3f} | {rest / res.steps * 1e3:.3f} | {rest / wall:.1%} |")
    raw.save(__file__, {"particles": model.n, "grid_shape": list(est.mpm.grid_shape), "steps": res.steps, "frame_s": wall,
                               "seconds": dict(times), "calls": dict(counts), "launch_overhead_us": overhead})
    print(f"| (of the launches: launch overhead, {overhead:.1f} us each) | {n_launch} | {n_launch * overhead * 1e-6:.3f} | "
          f"{n_launch * overhead * 1e-3 / res.steps:.3f} | {n_launch * overhead * 1e-6 / wall:.1%} |")


if __name__ == "__main__":
    main()
