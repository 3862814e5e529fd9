"""Register a cine slice to the stored slice: the 2D affine a frame's targets come from.

    python examples/example_register_slice.py --angle-deg 3 --shift-mm 2 -1.5

A known in-plane motion (rotation, then translation, about the volume centre) is applied to an
axial slice of the phantom image through the pancreas; :func:`warpmpm.registration.register_slices`
recovers it from the two images. Printed: the true and recovered ``A`` and ``t``, the error on the
organs' pixels in mm, and the time.
"""

import argparse
import math


import numpy as np

from warpmpm import InPlaneAffine, make_phantom
from warpmpm.registration import register_slices, resample_slice_affine
from warpmpm.imaging import slice_mask
from warpmpm.slices import extract_slice


class Example:
    def __init__(self, angle_deg=3.0, shift_mm=(2.0, -1.5), resolution=1.0):
        case = make_phantom(resolution=resolution)
        pan = case.organ_mask("pancreas")
        k = int(np.median(np.nonzero(pan)[0]))  # the mid-pancreas axial slice (array axis 0 is z)
        self.centre = case.geometry.center_mm()
        a = math.radians(angle_deg)
        self.truth = InPlaneAffine([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], shift_mm)
        self.stored = extract_slice(case.image, case.geometry, "axial", k, self.centre)
        self.captured = resample_slice_affine(self.stored, self.truth.A, self.truth.t_mm)
        self.mask = slice_mask(case.labels, case.geometry, "axial", k, self.centre, list(case.label_map.values()))
        self.result = None

    def step(self):
        self.result = register_slices(self.stored, self.captured, self.centre, mask=self.mask)

    def error_mm(self) -> float:
        """Mean distance between the true and the registered motion over the organ pixels of the slice (mm)."""
        jj, ii = np.nonzero(np.asarray(__import__("SimpleITK").GetArrayFromImage(self.mask)))
        o, sp = np.asarray(self.mask.GetOrigin()), np.asarray(self.mask.GetSpacing())
        uv = np.stack([o[0] + ii * sp[0], o[1] + jj * sp[1]], axis=1)
        got = self.result.affine
        return float(np.linalg.norm(uv @ (got.A - self.truth.A).T + (got.t_mm - self.truth.t_mm), axis=1).mean())

    def render(self):
        r = self.result
        np.set_printoptions(precision=4, suppress=True)
        print(f"true A {self.truth.A.ravel()}, t {self.truth.t_mm} mm")
        print(f"got  A {r.A.ravel()}, t {r.t_mm} mm ({r.iterations} iterations, {r.wall_s * 1e3:.0f} ms, {r.stop})")
        print(f"error on the organs' pixels: {self.error_mm():.3f} mm")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--angle-deg", type=float, default=3.0)
    p.add_argument("--shift-mm", type=float, nargs=2, default=(2.0, -1.5))
    p.add_argument("--resolution", type=float, default=1.0, help="phantom voxel size factor")
    a = p.parse_args(argv)
    ex = Example(a.angle_deg, tuple(a.shift_mm), a.resolution)
    ex.step()
    ex.render()
    return ex


if __name__ == "__main__":
    main()
