"""Time and accuracy of the 2D slice-to-slice registration on a 256 x 256 slice.

A phantom axial slice through the pancreas is resampled to 256 x 256 pixels (1.0 mm), moved by a
known in-plane affine (2 deg rotation, 1.5 deg shear, scale 0.9, translation (5, -3) mm) and
registered back. Prints median time per registration and the RMS error over the organ pixels, for
each metric of ITK's registration, at the default random sampling of 25 % of the organ-box pixels and at full
sampling, and for the Gauss-Newton backend (every mask pixel, the correlation metric); then both backends at
cine-frame pixel sizes.

    python benchmarks/registration_speed.py [--raw default]
"""

import argparse
import os
import time
from contextlib import nullcontext

import numpy as np
import SimpleITK as sitk


from warpmpm.experiment import raw_numbers as raw
from warpmpm.phantom import make_phantom
from warpmpm.registration import one_itk_thread, register_slices, resample_slice_affine
from warpmpm.imaging import slice_mask
from warpmpm.slices import extract_slice


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--raw", type=raw.check_name, default="default", help="the run's name in benchmarks/results/registration_speed.json")
    a = p.parse_args()
    case = make_phantom(seed=0)
    g = case.geometry
    k = int(np.median(np.nonzero(case.labels == case.label_map["pancreas"])[0]))
    centre = g.center_mm()
    s = extract_slice(case.image, g, "axial", k, centre)
    m = slice_mask(case.labels, g, "axial", k, centre, case.label_map.values())
    ref = sitk.Image(256, 256, sitk.sitkFloat32)
    ref.SetSpacing((1.0, 1.0))
    ref.SetOrigin((-128.0, -128.0))
    stored = sitk.Resample(s, ref, sitk.Transform(), sitk.sitkLinear, 0.0)
    mask = sitk.Resample(m, ref, sitk.Transform(), sitk.sitkNearestNeighbor, 0)
    r, gg, sc = np.deg2rad(2.0), np.deg2rad(1.5), 0.9
    A = np.array([[np.cos(r), -np.sin(r)], [np.sin(r), np.cos(r)]]) @ np.array([[1, np.tan(gg)], [np.tan(gg), 1]]) * sc
    t = np.array([5.0, -3.0])
    captured = resample_slice_affine(stored, A, t)
    jj, ii = np.nonzero(sitk.GetArrayFromImage(mask))
    pts = np.array([stored.TransformIndexToPhysicalPoint((int(i), int(j))) for i, j in zip(ii, jj)])
    print(f"slice 256x256, 1.0 mm, organ pixels {len(pts)}, {os.cpu_count()} cores")
    print("| metric | sampling | median ms | RMS error mm | iterations |")
    print("|---|---|---|---|---|")
    out = []
    for metric in ("correlation", "meansquares", "mattes"):
        for sampling in (0.25, 1.0):
            times, errs = [], []
            for rep in range(7):
                t0 = time.perf_counter()
                reg = register_slices(stored, captured, centre, mask=mask, metric=metric, sampling=sampling)
                times.append(time.perf_counter() - t0)
                errs.append(np.sqrt(np.mean(np.sum((pts @ reg.A.T + reg.t_mm - (pts @ A.T + t)) ** 2, axis=1))))
            print(f"| {metric} | {sampling} | {np.median(times) * 1e3:.1f} | {np.median(errs):.3f} | {reg.iterations} |")
            out.append({"metric": metric, "sampling": sampling, "times_s": times, "rms_errors_mm": errs, "iterations": reg.iterations})
    times, errs = [], []
    for rep in range(7):
        t0 = time.perf_counter()
        reg = register_slices(stored, captured, centre, mask=mask, backend="gauss-newton")
        times.append(time.perf_counter() - t0)
        errs.append(np.sqrt(np.mean(np.sum((pts @ reg.A.T + reg.t_mm - (pts @ A.T + t)) ** 2, axis=1))))
    print(f"| correlation, Gauss-Newton | 1.0 | {np.median(times) * 1e3:.1f} | {np.median(errs):.3f} | {reg.iterations} |")
    out.append({"metric": "correlation", "backend": "gauss-newton", "sampling": 1.0, "times_s": times, "rms_errors_mm": errs,
                "iterations": reg.iterations})
    # ITK's threads on a 2D slice: the default metric on ITK's default threads and on one (one_itk_thread, which the
    # organ-aware chain uses), 256 x 256 at 1 mm and the same slice at 2 and 3 mm pixels (cine-frame sizes)
    print("| pixels | backend | ITK threads | median ms | RMS error mm |")
    print("|---|---|---|---|---|")
    for px in (1.0, 2.0, 3.0):
        n = int(round(256 / px))
        ref2 = sitk.Image(n, n, sitk.sitkFloat32)
        ref2.SetSpacing((px, px))
        ref2.SetOrigin((-128.0, -128.0))
        st = sitk.Resample(stored, ref2, sitk.Transform(), sitk.sitkLinear, 0.0)
        mk = sitk.Resample(mask, ref2, sitk.Transform(), sitk.sitkNearestNeighbor, 0)
        cap = resample_slice_affine(st, A, t)
        for backend, one in (("itk", False), ("itk", True), ("gauss-newton", True)):
            times, errs = [], []
            for rep in range(9):
                t0 = time.perf_counter()
                with one_itk_thread() if one else nullcontext():
                    reg = register_slices(st, cap, centre, mask=mk, backend=backend)
                times.append(time.perf_counter() - t0)
                errs.append(np.sqrt(np.mean(np.sum((pts @ reg.A.T + reg.t_mm - (pts @ A.T + t)) ** 2, axis=1))))
            threads = 1 if one else sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
            print(f"| {n} x {n} ({px:g} mm) | {backend} | {threads} | {np.median(times) * 1e3:.1f} | {np.median(errs):.3f} |")
            out.append({"pixels_mm": px, "backend": backend, "itk_threads": threads, "times_s": times, "rms_errors_mm": errs})
    raw.save(__file__, out, run=a.raw)


if __name__ == "__main__":
    main()
