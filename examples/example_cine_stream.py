"""Follow a cine stream frame after frame: each frame starts from the last frame's state.

    python examples/example_cine_stream.py --frames 12

An axial slice through the pancreas moves as breathing would move it: an anterior-posterior
translation ``t(t) = amplitude * sin(2 pi t / period)``, one frame every ``1 / fps`` s. Each frame's
targets are that frame's slice motion applied to the slice particles' previous positions, and the
estimator starts from the previous frame's equilibrium (with its holding force), so a frame costs
far fewer steps than the first. Printed per frame: steps, latency, and how far the pancreas centroid
has moved against the slice's own translation.
"""

import argparse
import math
import time


import numpy as np
import warp as wp

from warpmpm import InPlaneAffine, build_model, make_phantom
from warpmpm.driving import SliceDrivenEstimator
from warpmpm.slices import DrivingSlice, in_plane_axes
from warpmpm.solvers import SolverConfig
from warpmpm.targets import affine_targets


class Example:
    def __init__(self, amplitude_mm=4.0, period_s=4.0, fps=4.0, resolution=3.0, organs="psdl", device="cpu"):
        case = make_phantom(resolution=resolution)
        self.model = m = build_model(case, organs)
        k = int(np.median(m.voxel_ijk[m.organ_slice("pancreas"), 2]))
        self.slices = [DrivingSlice("axial", k)]
        self.centre = case.geometry.center_mm()
        self.amplitude_mm, self.period_s, self.fps = amplitude_mm, period_s, fps
        e_u, e_v = in_plane_axes(m, "axial")
        self.e_v = e_v  # the image's second in-plane axis: anterior-posterior for an axial slice
        reach = [m.positions_mm + s * amplitude_mm * e_v for s in (-1.0, 1.0)]  # the grid covers the whole stroke
        self.estimator = SliceDrivenEstimator(m, self.slices, solver_config=SolverConfig(device=device),
                                              extra_points_mm=np.vstack(reach))
        self.pancreas = m.organ_slice("pancreas")
        self.frame = 0
        self.shift_mm = 0.0
        self.log = []

    def slice_shift_mm(self, frame: int) -> float:
        return self.amplitude_mm * math.sin(2 * math.pi * frame / self.fps / self.period_s)

    def step(self):
        """One cine frame: this frame's slice motion relative to the last, applied to the last state."""
        self.frame += 1
        new = self.slice_shift_mm(self.frame)
        move = InPlaneAffine(np.eye(2), [0.0, new - self.shift_mm])
        self.shift_mm = new
        before = self.estimator.positions_mm()
        _, targets = affine_targets(self.model, before, self.slices, [move], self.centre)
        t0 = time.perf_counter()
        r = self.estimator.estimate(targets)
        wall = time.perf_counter() - t0
        centroid = (r.positions_mm[self.pancreas] - self.model.positions_mm[self.pancreas]).mean(0) @ self.e_v
        self.log.append({"frame": self.frame, "slice_shift_mm": new, "pancreas_shift_mm": float(centroid),
                         "steps": r.steps, "wall_s": wall, "converged": r.converged})

    def render(self):
        f = self.log[-1]
        print(f"frame {f['frame']:3d}: slice {f['slice_shift_mm']:+.2f} mm, pancreas centroid {f['pancreas_shift_mm']:+.2f} mm, "
              f"{f['steps']} steps, {f['wall_s'] * 1e3:.0f} ms{'' if f['converged'] else ' (NOT converged)'}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--amplitude-mm", type=float, default=4.0)
    p.add_argument("--period-s", type=float, default=4.0)
    p.add_argument("--fps", type=float, default=4.0)
    p.add_argument("--resolution", type=float, default=3.0, help="phantom voxel size factor")
    p.add_argument("--device", default="cpu")
    a = p.parse_args(argv)
    wp.config.log_level = wp.LOG_ERROR
    ex = Example(a.amplitude_mm, a.period_s, a.fps, a.resolution, device=a.device)
    for _ in range(a.frames):
        ex.step()
        ex.render()
    lat = np.array([f["wall_s"] for f in ex.log[1:]] or [ex.log[0]["wall_s"]]) * 1e3
    print(f"latency after the first frame: median {np.median(lat):.0f} ms, p95 {np.percentile(lat, 95):.0f} ms")
    return ex


if __name__ == "__main__":
    main()
