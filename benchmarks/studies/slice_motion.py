"""Study (2026-11-23 to 2026-12-02; answer in benchmarks/studies/README.md). Slice motion the physics can use (issue 14): every target kind and drive mode on the contact protocol,
beside ``propagate`` with the same slice motion, on the real samples.

    python benchmarks/studies/slice_motion.py [--cases totalseg_mr,totalseg_ct] [--deformations 1,2,3,4,5,6] [--workers 2]
    python benchmarks/studies/slice_motion.py --protocol paper --cases totalseg_mr --deformations 1,2,3,4,5,6,7,8 --conditions a

``--registration itk,gauss-newton`` runs every ``registration*`` target kind with each slice registration backend
in the same task (the table labels the kind with its backend).

Conditions: ``a`` one mid-pancreas axial slice; ``sc`` a sagittal and a coronal slice through the middle of
the pancreas (the Unity set-up). Prints one table per condition (means over cases x deformations) and
writes every run to ``benchmarks/results/slice_motion_<protocol>.json``.
"""

import argparse
import os
import warnings
from dataclasses import replace

import numpy as np


from warpmpm.experiment import raw_numbers as raw
from warpmpm.experiment import CaseConfig, make_ground_truth, prepare_case, run_prepared
from warpmpm.experiment.tasks import run_tasks

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data")
KINDS = [("gt", "pinned"), ("gt-inplane", "inplane"), ("gt-inplane", "pinned"), ("affine", "inplane"), ("affine", "pinned"),
         ("registration", "inplane"), ("registration", "pinned"), ("registration-affine", "inplane"),
         ("registration-affine", "pinned"), ("registration-bspline", "inplane"), ("registration-bspline", "pinned"),
         ("registration-demons", "inplane"), ("registration-demons", "pinned")]


def mid_slices(prep, condition):
    m = prep.full_model
    pan = m.voxel_ijk[m.organ_slice("pancreas")]
    if condition == "a":
        return f"axial:{int(np.median(pan[:, 2])) + prep.offset[2]}"
    return f"sagittal:{int(np.median(pan[:, 0])) + prep.offset[0]},coronal:{int(np.median(pan[:, 1])) + prep.offset[1]}"


def task(name, deformation, protocol, conditions, kinds, backends=("itk",), passes=(1,)):
    warnings.simplefilter("ignore")
    cfg = CaseConfig(estimator="slice-driven", labels=os.path.join(DATA, name, "labels.nii.gz"), image=os.path.join(DATA, name, "image.nii.gz"), preset=name,
                     protocol=protocol, deformation=deformation, device="cpu",
                     baselines=("initial", "propagate", "volume_registration"))
    prep = prepare_case(cfg)
    gt = make_ground_truth(prep, cfg)
    rows = []
    for cond in conditions:
        slices = mid_slices(prep, cond)
        reg = [(b, p) for b in backends for p in (passes if "," in slices else (1,))]
        runs = [(kind, drive, b, p) for kind, drive in kinds for b, p in (reg if kind.startswith("registration") else [("itk", 1)])]
        for n, (kind, drive, backend, npass) in enumerate(runs):
            c = replace(cfg, slices=slices, targets=kind, drive=drive, exclude_driven=True, registration=backend,
                        registration_passes=npass, baselines=cfg.baselines if n == 0 else ("propagate",))
            out = run_prepared(prep, gt, c)
            r = {k: v.to_json() for k, v in out.results.items()}
            rows.append({"case": name, "deformation": deformation, "condition": cond, "slices": slices, "targets": kind, "drive": drive,
                         "backend": backend, "passes": npass, "results": r, "registration": out.registration,
                         "target_in_plane_error_mm": out.target_in_plane_error_mm, "steps": out.estimate.steps})
    return rows


def table(rows, cond):
    rs = [r for r in rows if r["condition"] == cond]
    if not rs:
        return ""
    base = {}
    for r in rs:
        for k in ("initial", "volume_registration"):
            if k in r["results"]:
                base.setdefault(k, {})[(r["case"], r["deformation"])] = r["results"][k]["error_offslice_mm"]
    lines = [f"condition {cond} ({rs[0]['slices']} ...): pancreas error without the driven particles, mm, mean over "
             f"{len({(r['case'], r['deformation']) for r in rs})} runs",
             "| targets | drive | estimate | propagate (same slice motion) | estimate vs propagate | target in-plane error | steps |",
             "|---|---|---|---|---|---|---|"]
    for (kind, drive), backend, npass in [(k, b, n) for k in KINDS for b in ("itk", "gauss-newton") for n in range(1, 6)]:
        sel = [r for r in rs if r["targets"] == kind and r["drive"] == drive and r.get("backend", "itk") == backend
               and r.get("passes", 1) == npass]
        if not sel:
            continue
        label = kind if backend == "itk" or not kind.startswith("registration") else f"{kind} (gauss-newton)"
        if npass > 1:
            kept = np.mean([r["registration"].get("passes", 1) for r in sel])
            label += f", {npass} passes ({kept:.1f} kept)"
        e = np.array([r["results"]["estimate"]["error_offslice_mm"] for r in sel])
        p = np.array([r["results"]["propagate"]["error_offslice_mm"] for r in sel])
        t = np.array([r["target_in_plane_error_mm"] for r in sel])
        reg = [r["registration"] for r in sel if r.get("registration")]
        ms = f", {1e3 * np.median([g['wall_s'] for g in reg]):.0f} ms a slice" if reg and "wall_s" in reg[0] else ""
        med = f", registration median {np.median([g['median_error_mm'] for g in reg]):.2f} mm" if reg and "median_error_mm" in reg[0] else ""
        pl = [r["results"]["propagate_planes"]["error_offslice_mm"] for r in sel if "propagate_planes" in r["results"]]
        planes = f" (all planes: {np.mean(pl):.2f})" if pl else ""
        lines.append(f"| {label}{med}{ms} | {drive if kind != 'gt' else '3d'} | {e.mean():.2f} | {p.mean():.2f}{planes} | {100 * (e.mean() / p.mean() - 1):+.0f} % "
                     f"({int(np.sum(e < p))} of {len(e)} better) | {np.nanmean(t):.2f} | {np.mean([r['steps'] for r in sel]):.0f} |")
    for k, v in base.items():
        lines.append(f"| {k} | | {np.mean(list(v.values())):.2f} | | | | |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default="totalseg_mr,totalseg_ct")
    p.add_argument("--deformations", default="1,2,3,4,5,6")
    p.add_argument("--protocol", default="contact", choices=["contact", "paper"])
    p.add_argument("--conditions", default="a,sc")
    p.add_argument("--kinds", default=None, help="comma-separated target:drive pairs (default: all)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--registration", default="itk", help="slice registration backends for the registration* kinds: itk, gauss-newton or both")
    p.add_argument("--passes", default="1", help="registration passes for the registration* kinds on several planes, e.g. 1,3")
    p.add_argument("--name", type=raw.check_name, default=None, help="the run's name in benchmarks/studies/results/slice_motion.json (default: the protocol)")
    a = p.parse_args(argv)
    cases = [c for c in a.cases.split(",") if os.path.exists(os.path.join(DATA, c, "labels.nii.gz"))]
    for c in set(a.cases.split(",")) - set(cases):
        print(f"skipping {c}: not in {DATA}")
    kinds = [tuple(k.split(":")) for k in a.kinds.split(",")] if a.kinds else KINDS
    rows = []
    backends = tuple(a.registration.split(","))
    passes = tuple(int(n) for n in a.passes.split(","))
    args = [(c, int(d), a.protocol, a.conditions.split(","), kinds, backends, passes) for c in cases for d in a.deformations.split(",")]

    def keep(rs):
        rows.extend(rs)
        print(f"{rs[0]['case']} def{rs[0]['deformation']}: " + ", ".join(
            f"{r['condition']} {r['targets']}/{r['drive']}/{r['backend']}/{r['passes']} {r['results']['estimate']['error_offslice_mm']:.2f}" for r in rs),
            flush=True)

    failed = run_tasks(task, args, keep, workers=a.workers)
    for cond in a.conditions.split(","):
        print("\n" + table(rows, cond))
    raw.save(__file__, run=a.name or a.protocol, data={"rows": rows, "failed": [str(f) for f in failed]})


if __name__ == "__main__":
    main()
