"""Build the particle model of a planning case: one particle per labelled voxel, positions in world mm.

    python examples/example_build_model.py                       # the built-in phantom
    python examples/example_build_model.py --labels ../shared/data/totalseg_mr/labels.nii.gz --preset totalseg_mr

Prints the particles per organ, the particle volume and mass, and the particles each organ has on the
axial slices through the pancreas: the features the selection model reads.
"""

import argparse


import numpy as np

from warpmpm import build_model, load_case, make_phantom


class Example:
    def __init__(self, labels=None, preset="amos", organs="psdl", phantom_resolution=2.0, particle_step=1):
        # a label map with its geometry (origin, spacing, direction): positions come out in world mm
        self.case = load_case(labels, preset=preset) if labels else make_phantom(resolution=phantom_resolution)
        # one particle per voxel of each organ; volume = voxel volume (x step^2), mass = density x volume
        self.model = build_model(self.case, organs, sampling_step=particle_step)

    def step(self):
        """Nothing moves here: the model is built once and read."""

    def render(self):
        m = self.model
        print(f"case {self.case.name}: grid {self.case.geometry.size} voxels of {self.case.geometry.spacing_mm} mm")
        print(f"{m.n} particles: {m.counts()}; particle volume {m.volume_mm3[0]:.2f} mm^3, "
              f"total mass {m.mass_kg().sum() * 1e3:.1f} g")
        counts = m.slice_counts("axial")
        ks = np.unique(m.voxel_ijk[m.organ_slice("pancreas"), 2])
        print("axial slice | " + " | ".join(m.organs))
        for k in ks:
            print(f"{k:11d} | " + " | ".join(str(c) for c in counts[k]))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--labels", help="a label map (default: the built-in phantom)")
    p.add_argument("--preset", default="amos", choices=["amos", "totalseg_ct", "totalseg_mr"])
    p.add_argument("--organs", default="psdl")
    p.add_argument("--phantom-resolution", type=float, default=2.0)
    p.add_argument("--particle-step", type=int, default=1)
    a = p.parse_args(argv)
    ex = Example(a.labels, a.preset, a.organs, a.phantom_resolution, a.particle_step)
    ex.render()
    return ex


if __name__ == "__main__":
    main()
