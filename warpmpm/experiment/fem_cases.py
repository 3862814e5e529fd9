"""The cases the finite-element benchmarks are measured on: the built-in phantom and the two real samples, loaded by
name, the frame of a truth where the pancreas moves most, and each plane where it shows the most pancreas.

The real samples are read from the folder ``WARPMPM_SAMPLE_DATA`` names, else from ``../shared/data`` beside the
checkout; they are never copied into the repository.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

__all__ = ["CASES", "PLANES", "sample_data_dir", "load", "load_on_disk", "peak_frame", "slices_through_pancreas", "field_run"]

#: case name -> (folder of the sample data, label preset)
CASES = {"mr": ("totalseg_mr", "totalseg_mr"), "ct": ("totalseg_ct", "totalseg_ct")}
#: plane-set name -> plane orientations
PLANES = {"sagittal": ("sagittal",), "sagittal+coronal": ("sagittal", "coronal"), "axial": ("axial",),
          "axial+sagittal+coronal": ("axial", "sagittal", "coronal")}


def sample_data_dir() -> str:
    """``$WARPMPM_SAMPLE_DATA``, else ``../shared/data`` beside the checkout holding this package."""
    env = os.environ.get("WARPMPM_SAMPLE_DATA")
    if env:
        return os.path.abspath(env)
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    return os.path.abspath(os.path.join(root, "..", "shared", "data"))


def load(name: str):
    """``(case, preset, image_path, labels_path)`` of ``phantom`` (paths ``None``: it lives in memory), ``mr`` or ``ct``;
    ``SystemExit`` with the reason when a sample is absent (a benchmark skips it visibly)."""
    from ..images import load_case
    from ..phantom import make_phantom

    if name == "phantom":
        return make_phantom(seed=1), "amos", None, None
    if name not in CASES:
        raise SystemExit(f"unknown case {name!r}: use phantom, {', '.join(CASES)}")
    folder, preset = CASES[name]
    data = sample_data_dir()
    lab, img = os.path.join(data, folder, "labels.nii.gz"), os.path.join(data, folder, "image.nii.gz")
    if not os.path.exists(lab):
        raise SystemExit(f"skipped {name}: the sample data is not at {data} (set WARPMPM_SAMPLE_DATA)")
    return load_case(lab, img, preset), preset, img, lab


def load_on_disk(name: str, folder: str):
    """:func:`load`, with the phantom written to ``folder`` (``image.nii.gz``, ``labels.nii.gz``; kept if there) so every
    case has files the commands can read and is read back from them; None, with the reason printed, when a sample is
    absent (a benchmark skips it visibly)."""
    from ..images import load_case, write_case

    try:
        case, preset, img, lab = load(name)
    except SystemExit as e:
        print(e)
        return None
    if img is None:
        os.makedirs(folder, exist_ok=True)
        img, lab = os.path.join(folder, "image.nii.gz"), os.path.join(folder, "labels.nii.gz")
        if not os.path.exists(lab):
            write_case(case, lab, img)
        case = load_case(lab, img, preset)
    return case, preset, img, lab


def peak_frame(series) -> int:
    """The frame of a finite-element truth series where the pancreas's mean displacement is largest."""
    return int(np.argmax([f["pancreas_mean_mm"] for f in series.record["frames"]]))


def slices_through_pancreas(cfg, planes) -> str:
    """Each plane where it shows the most of the pancreas (the layer of the run's particle model holding the most
    pancreas particles: a plane through the centroid can miss a curved pancreas; on the CT sample the median sagittal
    layer holds 3 of its particles), as a ``--slices`` string."""
    from .case import prepare_case

    prep = prepare_case(cfg)
    pan = prep.full_model.subset(("pancreas",))
    out = []
    for p in planes:
        counts = pan.slice_counts(p)[:, 0]
        out.append(prep.label(p, int(np.argmax(counts))))
    return ",".join(out)


def field_run(img: str, lab: str, preset: str, field_path: str, case_name: str, planes: str):
    """What a run on a field truth with the true in-plane motion of ``planes`` (a key of ``PLANES``) gives
    every method: ``(cfg, prep, model, truth positions, slices, RunTargets, the copy's positions)``."""
    from .baselines import propagate
    from .case import prepare_case
    from .config import CaseConfig
    from .target_kinds import run_targets
    from .truth import gt_for_model, make_ground_truth

    cfg = CaseConfig(estimator="slice-driven", image=img, labels=lab, preset=preset, protocol="field", truth_field=field_path, targets="gt-inplane",
                     device="cpu", particle_step=2 if case_name == "phantom" else 1)
    cfg = dataclasses.replace(cfg, slices=slices_through_pancreas(cfg, PLANES[planes]))
    prep = prepare_case(cfg)
    gt = make_ground_truth(prep, cfg)
    model = prep.model(cfg.organs)
    gt_pos = gt_for_model(gt, model)
    slices = prep.resolve_slices(model, cfg.slices)
    tg = run_targets(prep, gt, model, gt_pos, slices, cfg)
    copy = tg.combined_mm if tg.combined_mm is not None else propagate(
        model, slices[0], tg.affines[0], prep.centre_mm, tg.organ_affines.get(slices[0]))
    return cfg, prep, model, gt_pos, slices, tg, copy
