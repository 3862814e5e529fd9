"""The contact-protocol table of docs/results.md: the mid-pancreas axial slice, psdl, estimate with affine and with GT slice
targets beside the baselines, on phantom seeds and on the MR sample.

    python scripts/contact_table.py [--phantom-seeds 0,1,2] [--mr-seeds 1,2,3] [--json runs/contact.json]
"""

import argparse
import json
import os
import warnings
from dataclasses import replace


from warpmpm.experiment import CaseConfig, make_ground_truth, prepare_case, run_prepared

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--phantom-seeds", default="0,1,2")
    p.add_argument("--mr-seeds", default="1,2,3")
    p.add_argument("--deformation", type=int, default=1, help="contact scenario number")
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)
    warnings.simplefilter("ignore")
    cases = [(f"phantom seed {s}", CaseConfig(phantom_seed=int(s), particle_step=2)) for s in a.phantom_seeds.split(",") if s]
    mr = os.path.join(DATA, "totalseg_mr")
    if os.path.exists(os.path.join(mr, "labels.nii.gz")):
        cases += [(f"MR sample, seed {s}", CaseConfig(labels=os.path.join(mr, "labels.nii.gz"), image=os.path.join(mr, "image.nii.gz"),
                                                      preset="totalseg_mr", phantom_seed=int(s))) for s in a.mr_seeds.split(",") if s]
    else:
        print(f"skipping the MR sample: {mr} is absent")
    print("| case | neighbour motion | initial | propagate | volume_registration | estimate, affine targets | "
          "estimate, GT slice targets | off-slice error: affine / GT targets | slice |")
    print("|---|---|---|---|---|---|---|---|---|")
    raw = []
    for name, cfg in cases:
        cfg = replace(cfg, protocol="contact", deformation=a.deformation, device="cpu")
        prep = prepare_case(cfg)
        gt = make_ground_truth(prep, cfg)
        aff = run_prepared(prep, gt, cfg)
        gtt = run_prepared(prep, gt, replace(cfg, targets="gt", baselines=()))
        r = aff.results
        vr = r["volume_registration"].to_json()
        flag = " (uncertain)" if vr.get("uncertain") else ""
        motion = f"{gt.params['neighbour']} {gt.params['push_mm']:.1f} mm, swell {gt.params['swell']:.2f}"

        def cell(s):
            return f"{s.error_mm:.2f} / {s.dice:.3f}"

        print(f"| {name} | {motion} | {cell(r['initial'])} | {cell(r['propagate'])} | {cell(r['volume_registration'])}{flag} | "
              f"{cell(aff.estimate)} | {cell(gtt.estimate)} | {aff.estimate.error_offslice_mm:.2f} / {gtt.estimate.error_offslice_mm:.2f} | "
              f"{aff.slices[0]} |", flush=True)
        raw.append({"case": name, "affine": aff.to_json(), "gt_targets": gtt.to_json()})
    if a.json:
        with open(a.json, "w") as f:
            json.dump(raw, f, indent=1, default=str)


if __name__ == "__main__":
    main()
