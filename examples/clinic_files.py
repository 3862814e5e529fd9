"""The clinic's files end to end, on the built-in phantom: DICOM planning data in, contours, registrations and DVHs out.

    python examples/clinic_files.py --out runs/clinic

1. "The clinic's export": the phantom's planning image as a DICOM MR series, its organs as an RT Structure Set with
   the names a planning system gives them (Pancreas, Stomach, Duodenum, Kidney_L), and a plan dose as an RT Dose
   (50 Gy on the pancreas falling off over a few mm: motion matters at its edge).
2. A cine (synthetic: breathing and a push, `warpmpm make-cine`, interleaved sagittal / coronal DICOM frames).
3. One command, as a user runs it on their own data::

       warpmpm track --image OUT/clinic/planning --rtstruct OUT/clinic/RS.dcm --cine OUT/cine/cine \\
                     --out OUT/track --dicom --dose OUT/clinic/RD.dcm

   giving OUT/track/dicom/frame_NNNN/{RS,REG}.dcm, OUT/track/dicom/RD_accumulated.dcm and OUT/track/dose/
   (dvh.csv, dose_metrics.csv, dvh.png).

Research software, not a medical device.
"""

import argparse
import csv
import os

import numpy as np


from warpmpm.cli import main as warpmpm

ROI_NAMES = {"pancreas": "Pancreas", "stomach": "Stomach", "duodenum": "Duodenum", "left_kidney": "Kidney_L"}


def plan_dose(case, plateau_gy=50.0, margin_mm=5.0, falloff_mm=2.0):
    """A dose of ``plateau_gy`` within ``margin_mm`` of the pancreas, falling off logistically over ``falloff_mm``."""
    import SimpleITK as sitk

    pancreas = case.labels == case.label_map["pancreas"]
    img = case.geometry.apply_to(sitk.GetImageFromArray(pancreas.astype(np.uint8)))
    outside_mm = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(img, insideIsPositive=False, squaredDistance=False,
                                                                     useImageSpacing=True))
    return plateau_gy / (1.0 + np.exp((outside_mm - margin_mm) / falloff_mm))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="runs/clinic")
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--phantom-resolution", type=float, default=2.0)
    p.add_argument("--device", default=None)
    a = p.parse_args(argv)
    from warpmpm.dicom_rt import write_rtdose, write_rtstruct, write_series
    from warpmpm.experiment.cine_series import same_session
    from warpmpm.images import load_case

    cine = os.path.join(a.out, "cine")
    if warpmpm(["make-cine", "--phantom-resolution", str(a.phantom_resolution), "--frames", str(a.frames), "--plane",
                "sagittal,coronal", "--out", cine]) != 0:
        raise SystemExit("make-cine failed")
    case = load_case(os.path.join(cine, "planning", "labels.nii.gz"), os.path.join(cine, "planning", "image.nii.gz"))
    clinic = os.path.join(a.out, "clinic")
    ref = write_series(case.intensity_image(), os.path.join(clinic, "planning"), "MR")
    write_rtstruct(os.path.join(clinic, "RS.dcm"), ref, {o: case.labels == v for o, v in case.label_map.items()}, ROI_NAMES,
                   label="plan")
    write_rtdose(os.path.join(clinic, "RD.dcm"), ref, plan_dose(case))
    same_session(os.path.join(cine, "cine"), ref)  # the cine of the planning MR's session: its frame of reference, patient
    track = os.path.join(a.out, "track")
    args = ["track", "--image", os.path.join(clinic, "planning"), "--rtstruct", os.path.join(clinic, "RS.dcm"), "--cine",
            os.path.join(cine, "cine"), "--out", track, "--dicom", "--dose", os.path.join(clinic, "RD.dcm"), "--overwrite"]
    if a.device:
        args += ["--device", a.device]
    if warpmpm(args) != 0:
        raise SystemExit("track failed")
    print(f"\n{'organ':<12} {'metric':<10} {'planned Gy':>11} {'accumulated Gy':>15}")
    for r in csv.DictReader(open(os.path.join(track, "dose", "dose_metrics.csv"))):
        if (r["organ"], r["metric"]) in {("pancreas", "D95_Gy"), ("pancreas", "D98_Gy"), ("duodenum", "D0.5cc_Gy"),
                                         ("duodenum", "Dmax_Gy"), ("stomach", "D0.5cc_Gy"), ("stomach", "Dmax_Gy")}:
            print(f"{r['organ']:<12} {r['metric']:<10} {float(r['planned']):>11.2f} {float(r['accumulated']):>15.2f}")
    print(f"\nwrote {track}/dicom (RS.dcm and REG.dcm per frame, RD_accumulated.dcm) and {track}/dose (dvh.png)")
    return track


if __name__ == "__main__":
    main()
