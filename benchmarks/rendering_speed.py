"""Rendering the estimate: time and fidelity of the far fill on a coarse grid, against the fill on every voxel.

The cine tracker renders its current estimate on each frame's plane (:func:`warpmpm.imaging.render_plane`) and
the ground truths warp the whole planning volume (:func:`warpmpm.imaging.warp_volume`). Both build the backward
displacement field by two normalised Gaussian fills, 4 mm near the organs and 25 mm far from them. ``now`` smooths
the far fill on cells of about a quarter of its width and, for a frame's slab, over everything within three far
sigmas of it, and returns a frame's field on its thickness only (the near fill smoothed across the slab, then along
the plane over that thickness); ``previous`` (the code before the fourteenth session, emulated in the same process)
smoothed the far fill on every voxel of the slab and returned the whole slab's field. On the default phantom (seed 0, 1.33 x 1.33 x 3 mm voxels, psdl, particle step 2: 28k particles) moved
by a smooth non-rigid motion (10 mm superior-inferior breathing that grows from one end of the body to the other,
3 degrees about the axial axis), for a 6 mm sagittal frame through the pancreas:

- time of ``render_plane`` and of ``warp_volume`` (medians, the two alternated in one process), and their ratio;
- the field's largest difference from the ``previous`` whole-volume field within 8 mm of the particles (where the
  near fill weighs) and elsewhere (mm);
- each frame render's mean and largest difference from the render through the whole-volume field (the ground
  truths' way), within about 8 mm of the organs, as a fraction of the image's range.

    python benchmarks/rendering_speed.py [--repeats 7]

Raw numbers: ``benchmarks/results/rendering_speed.json``.
"""

import argparse
import statistics
import sys
import time
from contextlib import nullcontext

import numpy as np
import SimpleITK as sitk


from warpmpm.experiment import raw_numbers as raw
from warpmpm import imaging
from warpmpm.model import build_model
from warpmpm.phantom import make_phantom


class Previous:
    """Inside ``with``: the far fill on every voxel of the field's own grid (the code before the coarse far fill)."""

    def __enter__(self):
        self.cells, self.field = imaging.FAR_CELLS_PER_SIGMA, imaging.backward_displacement
        imaging.FAR_CELLS_PER_SIGMA = 1e9
        imaging.backward_displacement = lambda g, p, x, s=4.0, f=25.0, **ignored: self.field(g, p, x, s, f)

    def __exit__(self, *exc):
        imaging.FAR_CELLS_PER_SIGMA, imaging.backward_displacement = self.cells, self.field


def moved_positions(positions_mm: np.ndarray) -> np.ndarray:
    """A smooth non-rigid motion: superior-inferior breathing from 0 to 10 mm along the body, 3 degrees about z."""
    c = positions_mm.mean(axis=0)
    z = (positions_mm[:, 2] - positions_mm[:, 2].min()) / np.ptp(positions_mm[:, 2])
    a = np.radians(3.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    out = (positions_mm - c) @ rot.T + c
    out[:, 2] += 10.0 * z
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=7)
    a = p.parse_args(argv)
    case = make_phantom(seed=0)
    model = build_model(case, "psdl", sampling_step=2)
    g = case.geometry
    planning, now = model.positions_mm, moved_positions(model.positions_mm)
    image = case.intensity_image()
    i = int(np.median(np.nonzero(case.organ_mask("pancreas"))[2]))
    thickness = 6.0
    plane = image[i:i + 1, :, :]
    sp = list(plane.GetSpacing())
    sp[0] = thickness
    plane.SetSpacing(sp)
    normal = np.array([1.0, 0.0, 0.0])

    def render():
        return sitk.GetArrayFromImage(imaging.render_plane(case, planning, now, plane, normal, thickness, planning_image=image))

    times = {k: [] for k in ("render_plane previous", "render_plane now", "warp_volume previous", "warp_volume now")}
    out = {}
    for r in range(a.repeats):
        for method in (("previous", "now") if r % 2 == 0 else ("now", "previous")):
            with Previous() if method == "previous" else nullcontext():
                t = time.perf_counter()
                out["render " + method] = render()
                times["render_plane " + method].append(time.perf_counter() - t)
                t = time.perf_counter()
                imaging.warp_volume(case, planning, now)
                times["warp_volume " + method].append(time.perf_counter() - t)
                if r == 0:
                    out["field " + method] = sitk.GetArrayFromImage(imaging.backward_displacement(g, planning, now))
    # the render through the whole-volume field of the previous code: the ground truths' way
    keep = imaging.slab_region
    imaging.slab_region = lambda geometry, *args, **kw: ((0, 0, 0), tuple(geometry.size))
    with Previous():
        whole = render()
    imaging.slab_region = keep

    ijk = np.rint(g.world_to_index(now)).astype(int)
    inside = np.all((ijk >= 0) & (ijk < np.asarray(g.size)), axis=1)
    occupied = np.zeros(g.size[::-1], dtype=np.uint8)
    occupied[ijk[inside, 2], ijk[inside, 1], ijk[inside, 0]] = 1
    dist = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(g.apply_to(sitk.GetImageFromArray(occupied)), insideIsPositive=False,
                                                              squaredDistance=False, useImageSpacing=True))
    near = dist < 8.0
    diff = np.abs(out["field now"] - out["field previous"]).max(axis=-1)
    around = sitk.GetArrayFromImage(sitk.Resample(g.apply_to(sitk.GetImageFromArray(dist.astype(np.float32))), plane, sitk.Transform(),
                                                  sitk.sitkLinear, 1e9)) < 8.0
    rng = float(np.ptp(whole))
    med = {k: 1e3 * statistics.median(v) for k, v in times.items()}
    rows = {"times_ms": med, "raw_times_s": times,
            "render_plane_ratio": med["render_plane now"] / med["render_plane previous"],
            "warp_volume_ratio": med["warp_volume now"] / med["warp_volume previous"],
            "field_diff_near_max_mm": float(diff[near].max()), "field_diff_near_mean_mm": float(diff[near].mean()),
            "field_diff_far_max_mm": float(diff[~near].max()), "field_diff_far_mean_mm": float(diff[~near].mean()),
            "field_diff_by_distance_mm": {f"{lo}-{hi}": {"max": float(diff[(dist >= lo) & (dist < hi)].max()),
                                                         "mean": float(diff[(dist >= lo) & (dist < hi)].mean())}
                                          for lo, hi in ((8, 40), (40, 60), (60, 1000)) if np.any((dist >= lo) & (dist < hi))},
            "field_max_mm": float(np.abs(out["field previous"]).max())}
    for method in ("previous", "now"):
        d = np.abs(out["render " + method] - whole)[around] / rng
        rows[f"render_{method}_vs_whole_mean"] = float(d.mean())
        rows[f"render_{method}_vs_whole_max"] = float(d.max())
    print(f"default phantom, {model.n} particles, grid {g.size}; a 6 mm sagittal frame through the pancreas, slab "
          f"{imaging.slab_region(g, plane, normal, thickness / 2 + 12.0)}")
    print("| step | previous ms | now ms | now / previous |")
    print("|---|---|---|---|")
    for what in ("render_plane", "warp_volume"):
        print(f"| {what} | {med[what + ' previous']:.0f} | {med[what + ' now']:.0f} | {rows[what + '_ratio']:.2f}x |")
    print(f"whole-volume field, now against previous: within 8 mm of the particles max {rows['field_diff_near_max_mm']:.3f} mm "
          f"(mean {rows['field_diff_near_mean_mm']:.4f}), elsewhere max {rows['field_diff_far_max_mm']:.3f} mm (mean "
          f"{rows['field_diff_far_mean_mm']:.4f}); the field reaches {rows['field_max_mm']:.1f} mm")
    print("  by distance from the particles: " + ", ".join(f"{k} mm max {v['max']:.3f} (mean {v['mean']:.4f})"
                                                      for k, v in rows["field_diff_by_distance_mm"].items()))
    print(f"frame render against the render through the whole-volume field, within 8 mm of the particles (fraction of the "
          f"image range): previous mean {rows['render_previous_vs_whole_mean']:.2e} max {rows['render_previous_vs_whole_max']:.3f}; "
          f"now mean {rows['render_now_vs_whole_mean']:.2e} max {rows['render_now_vs_whole_max']:.3f}")
    raw.save(__file__, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
