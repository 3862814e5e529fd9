"""Markdown tables of results: one run (:func:`format_table`), the paper-form sweep summary
(:func:`summarize`) and the multi-direction table beside the paper's (:func:`summarize_multi`)."""

from __future__ import annotations

import math

import numpy as np

from ..images import COMBINATIONS
from .result import RunResult

__all__ = ["PAPER_MULTI", "MULTI_CONDITIONS", "MULTI_NAMES", "format_table", "summarize", "summarize_multi"]

#: The paper's multi-direction table (20 MR cases x 8 deformations, psdl, GT targets, driven particles excluded):
#: condition -> (error mm, sd mm, Dice).
PAPER_MULTI = {"a": (4.26, 1.16, 0.610), "ac": (3.12, 0.989, 0.636), "as": (2.42, 0.584, 0.650), "asc": (2.13, 0.598, 0.662)}
MULTI_CONDITIONS = ("a", "ac", "as", "asc")
MULTI_NAMES = {"a": "axial only", "ac": "axial + coronal", "as": "axial + sagittal", "asc": "axial + sagittal + coronal"}


def format_table(out: RunResult) -> str:
    """The run's table: each baseline and the estimate with error, p95, Dice (and steps, time)."""
    rows = ["| method | error mm (all particles) | off-slice error mm (driven left out) | p95 mm | Dice | steps | wall s |", "|---|---|---|---|---|---|---|"]
    names = ("initial", "propagate", "propagate_affine", "propagate_planes", "rigid", "volume_registration", "completion", "copy",
             "slice-driven", "estimate")
    for name in names:
        r = out.results.get(name)
        if r is None or (name == out.estimator and "estimate" in out.results):
            continue  # the estimate's own row says which estimator it is
        j = r.to_json()
        steps = str(j.get("steps", ""))
        wall = f"{j['wall_s']:.2f}" if "wall_s" in j else ""
        label = f"estimate ({out.estimator})" if name == "estimate" else name
        if j.get("worse_than_no_motion"):
            label += " (FLAGGED: matches the planes worse than no motion)"
        elif j.get("fallback_to_identity"):
            label += " (FAILED: fell back to no motion)"
        elif name == "completion" and not j.get("converged", True):
            label += f" (NOT converged: residual {j['residual']:.1e})"
        elif name in ("estimate", "copy", "slice-driven") and j.get("flag"):
            label += " (FLAGGED: worse than no motion by its own measure)" if "worse" in j["flag"] else " (nothing driven)"
        elif j.get("uncertain"):
            label += f" (uncertain: two registrations disagree by {j['disagreement_mm']:.1f} mm)"
        rows.append(f"| {label} | {r.error_mm:.2f} | {r.error_offslice_mm:.2f} | {r.p95_mm:.2f} | {r.dice:.3f} | {steps} | {wall} |")
    truth = (f"protocol field ({out.gt.get('made_by', '')}: {out.gt.get('truth_field', '')})" if out.protocol == "field" else
             f"protocol {out.protocol} (deformation {out.deformation})")
    head = (f"case {out.case}, organs {out.organs}, slices {','.join(out.slices)}, {truth}, targets {out.targets} (drive {out.drive}), device {out.device}, "
            f"particles {sum(out.n_particles.values())} ({out.n_particles}), driven {out.n_driven}")
    est = out.results.get("slice-driven")
    if est is None:
        est = out.estimate
    state = ("converged" if est.converged else "STALLED" if est.reason == "stalled" else
             "NOT converged: the driven particles stopped but the model had not settled" if getattr(est, "slice_converged", False)
             else "NOT converged")
    if getattr(est, "finished_by", "explicit") == "copy":
        tail = "estimate (copy): the planes' observed motion, no solve"
    elif getattr(est, "finished_by", "explicit") == "quasistatic":
        tail = (f"slice-driven (quasi-static): {state} ({est.reason}) in {est.steps} Newton iterations, {est.ms_per_step:.1f} ms each, "
                f"RMS residual {est.rms_residual_mm:.3f} mm; "
                + ("the whole model had settled" if est.settled else
                   f"the last iteration still moved a particle {est.body_motion_mm:.3f} mm: not yet an equilibrium"))
    else:
        before = (f" after {est.linear_iterations} conjugate-gradient iterations of an unsettled quasi-static start"
                  if getattr(est, "finished_by", "") == "quasistatic+explicit" else "")
        tail = (f"slice-driven: {state} ({est.reason}) in {est.steps} steps{before}, {est.ms_per_step:.2f} ms/step, "
                f"RMS residual {est.rms_residual_mm:.3f} mm; "
                + ("the whole model had settled" if est.settled else
                   f"the model was still moving ({est.body_motion_mm:.2f} mm per 100 steps at the 99th percentile: "
                   "not yet an equilibrium; --wait-settled runs on until it is)"))
    if out.registration is not None:
        r = out.registration
        tail += f"\nregistration: in-plane error of the slice's pancreas particles {r['error_mm']:.2f} mm, {r['wall_s'] * 1e3:.1f} ms per slice"
        pc = r.get("plane_check")
        if pc:
            dropped = ", ".join(pc["dropped"]) or "none"
            tail += (f"\nplane check: planes' match (mean correlation) unmoved {pc['match_none']:.3f}, every plane's motion "
                     f"{pc['match_all']:.3f}, kept {pc['match_kept']:.3f}; not driven: {dropped}")
    chosen = out.estimate
    if not math.isnan(getattr(chosen, "plane_match", float("nan"))):
        tail += (f"\nestimate's own measure ({out.estimator}): planes' match {chosen.plane_match:.3f} (unmoved "
                 f"{chosen.plane_match_unmoved:.3f})")
        if chosen.flag:
            tail += f"; FLAGGED: {chosen.flag}"
    from .organs import format_organ_table

    organs = "\n\nevery organ (pancreas: the target; stomach, duodenum, left kidney: organs at risk):\n" + format_organ_table(out.results)
    return head + "\n" + "\n".join(rows) + "\n" + tail + organs


def summarize(rows: list[dict]) -> str:
    """Paper-form summary of sweep rows: best slice per (case, deformation, combination), then mean +- sd per
    combination, with no estimation and ``propagate`` on the same slice beside it. Failed rows are left out."""
    best: dict[tuple, dict] = {}
    for r in rows:
        if r.get("failure") or str(r.get("error_mm", "")) in ("", "nan"):
            continue
        key = (r["case"], r["deformation"], r["organs"])
        if key not in best or float(r["error_mm"]) < float(best[key]["error_mm"]):
            best[key] = r
    lines = ["| condition | error mm | Dice | n |", "|---|---|---|---|"]
    by_combo: dict[str, list] = {}
    for (case, d, combo), r in best.items():
        by_combo.setdefault(combo, []).append(r)
    any_rows = list(best.values())
    if any_rows:
        ie = np.array([float(r["initial_error_mm"]) for r in any_rows])
        idc = np.array([float(r["initial_dice"]) for r in any_rows])
        lines.append(f"| initial (no estimation) | {ie.mean():.2f} +- {ie.std():.2f} | {idc.mean():.3f} | {len(ie)} |")
    for combo in COMBINATIONS:
        if combo not in by_combo:
            continue
        rs = by_combo[combo]
        e = np.array([float(r["error_mm"]) for r in rs])
        dc = np.array([float(r["dice"]) for r in rs])
        pe = np.array([float(r["propagate_error_mm"]) for r in rs])
        lines.append(f"| {combo}, best slice | {e.mean():.2f} +- {e.std():.2f} | {dc.mean():.3f} +- {dc.std():.3f} | {len(e)} |")
        lines.append(f"| {combo}, propagate (same slice) | {pe.mean():.2f} +- {pe.std():.2f} | | {len(pe)} |")
    return "\n".join(lines)


def summarize_multi(rows: list[dict]) -> str:
    """The multi-direction table (mean +- sd over cases x deformations) beside the paper's."""
    lines = ["| condition | pick | error mm | Dice | initial error mm | 3D affine registration error mm | n | paper error mm | paper Dice |",
             "|---|---|---|---|---|---|---|---|---|"]
    picks = sorted({r["pick"] for r in rows}, key=lambda p: (p != "top1", p))
    for cond in MULTI_CONDITIONS:
        for pick in picks:
            rs = [r for r in rows if r["condition"] == cond and r["pick"] == pick]
            if not rs:
                continue
            e = np.array([float(r["error_mm"]) for r in rs])
            dc = np.array([float(r["dice"]) for r in rs])
            ie = np.array([float(r["initial_error_mm"]) for r in rs])
            ve = np.array([float(r.get("volume_registration_error_mm") or "nan") for r in rs])
            pe, psd, pdice = PAPER_MULTI[cond]
            paper = f"{pe:.2f} +- {psd:.2f} | {pdice:.3f}" if pick != "top1" else " | "
            lines.append(f"| {MULTI_NAMES[cond]} | {pick} | {e.mean():.2f} +- {e.std():.2f} | {dc.mean():.3f} +- {dc.std():.3f} | "
                         f"{ie.mean():.2f} +- {ie.std():.2f} | {ve.mean():.2f} +- {ve.std():.2f} | {len(e)} | {paper} |")
    return "\n".join(lines)
