"""The cine tracker's per-frame outputs: time to compute and write a frame's displacement field and label map.

With ``--displacement`` the tracker writes each frame's 3D displacement field (a vector image on the planning grid,
:func:`warpmpm.tracker.displacement_field`). ``now`` scatters the particles with ``np.bincount``, smooths only over
the particles' voxel box plus four sigmas, sets the field to exactly zero where its fade-out weight is below 1e-3
and writes float32; ``previous`` (the code before the fifteenth session, kept here as the same-run peer) scattered
with ``np.add.at``, smoothed the whole planning grid and wrote float64 with a vanishing but non-zero tail, which
gzip cannot shrink. On the default phantom (seed 0, psdl, particle step 2: 28k particles) under the smooth
non-rigid motion of ``rendering_speed.py`` (10 mm breathing growing along the body, 3 degrees about z):

- compute and write times (medians, the two alternated), the file sizes, and the ratio now / previous;
- the largest difference between the two fields where the fade-out weight is at least 1e-3 and elsewhere (mm);
- the label map (``--labels`` output, written for every frame) beside them, for scale.

    python benchmarks/output_speed.py [--repeats 5]

Raw numbers: ``benchmarks/results/output_speed.json``.
"""

import argparse
import os
import statistics
import sys
import tempfile
import time

import numpy as np
import SimpleITK as sitk


from warpmpm.experiment import raw_numbers as raw
from rendering_speed import moved_positions
from warpmpm.model import build_model
from warpmpm.phantom import make_phantom
from warpmpm.imaging import particle_label_map
from warpmpm.tracker import _write_image, displacement_field


def previous_field(model, positions_mm, case, sigma_mm: float = 4.0) -> sitk.Image:
    """The displacement field as the tracker computed it before the fifteenth session (the peer)."""
    g = case.geometry
    u = positions_mm - model.positions_mm
    ijk = np.clip(np.rint(g.world_to_index(model.positions_mm)).astype(int), 0, np.asarray(g.size) - 1)
    num = np.zeros(g.size[::-1] + (3,))
    den = np.zeros(g.size[::-1])
    np.add.at(num, (ijk[:, 2], ijk[:, 1], ijk[:, 0]), u)
    np.add.at(den, (ijk[:, 2], ijk[:, 1], ijk[:, 0]), 1.0)

    def smooth(a):
        return sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(g.apply_to(sitk.GetImageFromArray(a.astype(np.float32))), sigma_mm))

    d = smooth(den)
    f = np.stack([smooth(num[..., c]) for c in range(3)], axis=-1) / np.maximum(d, 1e-6)[..., None]
    f *= np.clip(d / max(float(d.max()), 1e-12) * 4.0, 0.0, 1.0)[..., None]
    return g.apply_to(sitk.GetImageFromArray(f.astype(np.float64), isVector=True))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=5)
    a = p.parse_args(argv)
    case = make_phantom(seed=0)
    model = build_model(case, "psdl", sampling_step=2)
    g = case.geometry
    now_mm = moved_positions(model.positions_mm)
    fields = {"previous": previous_field, "now": displacement_field}
    times = {f"{k} {m}": [] for m in fields for k in ("compute", "write")}
    times["labels compute+write"] = []
    sizes, out = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.repeats):
            for method in (("previous", "now") if r % 2 == 0 else ("now", "previous")):
                t = time.perf_counter()
                img = fields[method](model, now_mm, case)
                times[f"compute {method}"].append(time.perf_counter() - t)
                path = os.path.join(tmp, f"{method}.nii.gz")
                t = time.perf_counter()
                _write_image(img, path)
                times[f"write {method}"].append(time.perf_counter() - t)
                sizes[method] = os.path.getsize(path) / 1e6
                out[method] = sitk.GetArrayFromImage(sitk.ReadImage(path)).astype(np.float64)
            t = time.perf_counter()
            lab = particle_label_map(model, now_mm, {o: k + 1 for k, o in enumerate(model.organs)})
            _write_image(g.apply_to(sitk.GetImageFromArray(lab.astype(np.uint8))), os.path.join(tmp, "labels.nii.gz"))
            times["labels compute+write"].append(time.perf_counter() - t)
    med = {k: 1e3 * statistics.median(v) for k, v in times.items()}
    total = {m: med[f"compute {m}"] + med[f"write {m}"] for m in fields}
    # where the new field's fade-out weight is at least 1e-3: the same field; elsewhere it is zero
    kept = np.any(out["now"] != 0.0, axis=-1)
    diff = np.abs(out["now"] - out["previous"]).max(axis=-1)
    rows = {"times_ms": med, "raw_times_s": times, "file_mb": sizes, "total_ms": total, "ratio": total["now"] / total["previous"],
            "diff_where_kept_max_mm": float(diff[kept].max()), "diff_elsewhere_max_mm": float(diff[~kept].max()),
            "field_max_mm": float(np.linalg.norm(out["previous"], axis=-1).max()), "voxels_kept": float(kept.mean())}
    print(f"default phantom, {model.n} particles, planning grid {g.size}; medians of {a.repeats}")
    print("| output | compute ms | write ms | total ms | file MB |")
    print("|---|---|---|---|---|")
    for m in fields:
        print(f"| displacement field, {m} | {med['compute ' + m]:.0f} | {med['write ' + m]:.0f} | {total[m]:.0f} | {sizes[m]:.1f} |")
    print(f"| label map (every frame) | | | {med['labels compute+write']:.0f} | |")
    print(f"displacement field now / previous: {rows['ratio']:.2f}x; largest difference where kept {rows['diff_where_kept_max_mm']:.1e} mm, "
          f"where zeroed {rows['diff_elsewhere_max_mm']:.4f} mm (the field reaches {rows['field_max_mm']:.1f} mm; "
          f"{100 * rows['voxels_kept']:.0f} % of the voxels kept)")
    raw.save(__file__, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
