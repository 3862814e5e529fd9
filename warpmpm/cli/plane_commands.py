"""Where to image: ``plan-planes`` (rank cine-plane placements for a planning scan) and ``train-planes``."""

from __future__ import annotations

import sys

from ..errors import InputError

__all__ = ["cmd_plan_planes", "cmd_train_planes", "plan_planes"]

_SHORT = {"pancreas": "panc", "stomach": "stom", "duodenum": "duod", "left_kidney": "l.kid"}


def _planning_model(a):
    """The planning scan's particle model of every organ (uncropped: its slice indices are the scan's)."""
    from ..images import ORGANS, load_case
    from ..model import build_model
    from ..phantom import make_phantom

    if a.rtstruct:
        from ..dicom_rt import case_from_rtstruct
        from ..session import structure_mapping as _structure_mapping

        if a.labels:
            raise InputError("give the organs once: --labels (a label map) or --rtstruct (a structure set), not both")
        if a.image is None:
            raise InputError("--rtstruct needs --image, the DICOM planning series folder it refers to")
        case = case_from_rtstruct(a.image, a.rtstruct, _structure_mapping(a.structure), "psdl")
        step = a.particle_step or 1
    elif a.labels is None:
        if a.image is not None:
            raise InputError("--image needs its --labels (the organ label map of the planning scan) or --rtstruct")
        case = make_phantom(seed=a.phantom_seed, resolution=a.phantom_resolution, preset=a.preset)
        step = a.particle_step or 2
    else:
        if a.image is None:
            raise InputError("--labels needs its --image (the planning image)")
        case = load_case(a.labels, a.image, a.preset)
        step = a.particle_step or 1
    missing = [o for o in ORGANS if o not in case.label_map or not (case.labels == case.label_map[o]).any()]
    if missing:
        raise InputError(f"the planning labels lack {', '.join(missing)}: the placement model weighs all four organs "
                         f"(pancreas, stomach, duodenum, left kidney); check --preset ({a.preset})")
    return case, build_model(case, tuple(ORGANS), sampling_step=step), step


def plan_planes(model, placement_model, families, rank_by, top: int, stride: int = 1, motion_mm: float | None = None):
    """Rank the placements; returns (ranked, rule entries per family, wall seconds, printable lines)."""
    from ..plane_placement import FEATURES, pancreas_slices

    ranked, wall = placement_model.rank(model, families, rank_by, stride)
    organs = placement_model.organs
    col = {f: i for i, f in enumerate(FEATURES)}
    head = (f"{'#':>3}  {'planes':<24}" + "".join(f"{o[:11]:>12}" for o in organs)
            + "   " + " ".join(f"{'seen ' + _SHORT.get(o, o[:5]):>10}" for o in organs))
    unit = f"predicted error, mm, for {motion_mm:g} mm of motion" if motion_mm else "predicted fraction of the motion missed"
    lines = [f"plane placements for the {'+'.join(rank_by)}, best first ({unit}; 'seen': the organ's section on the planes "
             "over its largest section)", head]

    def fmt(rank, entry):
        p, x, pred = entry
        vals = "".join(f"{pred[o] * (motion_mm or 1):>12.3f}" if motion_mm else f"{pred[o]:>12.3f}" for o in organs)
        on = " ".join(f"{max(x[col[f'{o}_section_sagittal']], x[col[f'{o}_section_coronal']]):>10.2f}" for o in organs)
        return f"{rank:>3}  {p.label():<24}{vals}   {on}"

    lines += [fmt(i + 1, e) for i, e in enumerate(ranked[:top])]
    rules = {}
    best = {o: pancreas_slices(model, o)[0] for o in ("sagittal", "coronal")}  # the rule's slices
    for family in families:
        pos = next(i for i, e in enumerate(ranked) if e[0].family == family)  # the family's best
        rule_pos = next(i for i, e in enumerate(ranked) if e[0].family == family
                        and all(int(sl.index) == best[sl.orientation] for sl in e[0].slices))
        rules[family] = (rule_pos, ranked[rule_pos])
        lines.append(f"{family}: best #{pos + 1} {ranked[pos][0].label()}; the rule without a model (most pancreas on each "
                     f"plane) {ranked[rule_pos][0].label()} ranks #{rule_pos + 1}")
    lines.append(f"{len(ranked)} placements ranked in {wall * 1e3:.1f} ms")
    held = placement_model.trained_on.get("held_out")
    if held:
        for objective, fams in held["regret_mm"].items():
            if objective == "all_organs" and rank_by == ("pancreas",):
                continue
            lines.append(f"measured on held-out cases ({', '.join(held['cases'])}), judged by "
                         f"{objective.replace('_', ' ')}: mean regret (mm) " + "; ".join(
                             f"{fam} model {v['model']:.2f}, rule {v['rule']:.2f}" for fam, v in fams.items()))
        lines.append("for a ranking by this scan's own simulated motion (about a minute), use --method simulate (the default)")
    return ranked, rules, wall, lines


def cmd_plan_planes(a) -> int:
    """``warpmpm plan-planes``: the ranked placements of the cine planes for a planning scan."""
    from ..experiment.io import check_output_path, write_json_atomic
    from ..plane_placement import DEFAULT_PLACEMENT_MODEL, FAMILIES, PlacementModel, draw_placements

    families = tuple(f for f in a.families.split(",") if f)
    for f in families:
        if f not in FAMILIES:
            raise InputError(f"--families {f!r}: use {', '.join(FAMILIES)}")
    rank_by = tuple(o for o in a.rank_by.split(",") if o)
    if a.top < 1:
        raise InputError(f"--top must be >= 1, got {a.top}")
    if a.motion_mm is not None and not (0 < a.motion_mm < 100):
        raise InputError(f"--motion-mm is the organs' expected motion in mm (0-100), got {a.motion_mm}")
    for path, option in ((a.json, "--json"), (a.picture, "--picture")):
        if path:
            check_output_path(path, option, [("--image", a.image), ("--labels", a.labels), ("--rtstruct", getattr(a, "rtstruct", None)),
                                              ("--model", a.model)])
    if a.method == "simulate":
        return _simulate(a, families, rank_by)
    placement_model = PlacementModel.load(a.model or DEFAULT_PLACEMENT_MODEL)
    _, model, _ = _planning_model(a)
    ranked, rules, wall, lines = plan_planes(model, placement_model, families, rank_by, a.top, a.stride, a.motion_mm)
    print("\n".join(lines))
    if a.picture:
        draw_placements(model, ranked, a.picture, top=min(3, a.top))
        print(f"picture: {a.picture}")
    if a.json:
        doc = {"units": "predicted fraction of each organ's motion the estimate misses (method "
                        f"{placement_model.method!r}); offsets and distances in mm, world LPS",
               "rank_by": list(rank_by), "model": a.model or DEFAULT_PLACEMENT_MODEL, "ranking_s": wall,
               "placements": [{"rank": i + 1, "family": p.family, "planes": p.label(), "predicted_fraction_missed": pred,
                               "features": dict(zip(placement_model.features, map(float, x)))}
                              for i, (p, x, pred) in enumerate(ranked)],
               "rule": {f: {"rank": r + 1, "planes": e[0].label()} for f, (r, e) in rules.items()}}
        write_json_atomic(a.json, doc)
        print(f"ranking: {a.json}")
    return 0


def _simulation_case(a, case, work: str) -> dict:
    """The sweep's case dict of the planning scan (an RT Structure Set's organs written as a label map in ``work``)."""
    import os

    from ..images import write_case

    if a.rtstruct:
        labels, image = os.path.join(work, "labels.nii.gz"), os.path.join(work, "image.nii.gz")
        write_case(case, labels, image)
        return {"name": "planning", "labels": labels, "image": image, "preset": "amos"}
    if a.labels:
        return {"name": "planning", "labels": a.labels, "image": a.image, "preset": a.preset}
    return {"name": f"phantom{a.phantom_seed}", "phantom_seed": a.phantom_seed, "phantom_resolution": a.phantom_resolution}


def _simulate(a, families, rank_by) -> int:
    """``plan-planes --method simulate``: a finite-element breathing truth of the planning scan, every placement of the grid
    scored by the copy of its planes' true in-plane motion, ranked by the simulated error."""
    import tempfile
    import time

    import numpy as np

    from ..errors import SimulationError
    from ..experiment.io import write_json_atomic
    from ..experiment.plane_sweep import plane_sweep_task
    from ..images import ORGANS
    from ..plane_placement import Placement, draw_placements, is_rule
    from ..slices import parse_slices

    if a.positions < 1:
        raise InputError(f"--positions must be >= 1, got {a.positions}")
    if a.truth_seed < 0:
        raise InputError(f"--truth-seed must be >= 0, got {a.truth_seed}")
    if a.truth_cell_mm is not None and not (2.0 <= a.truth_cell_mm <= 30.0):
        raise InputError(f"--truth-cell-mm is the truth's mesh cell, 2-30 mm, got {a.truth_cell_mm}")
    bad = [o for o in rank_by if o not in ORGANS]
    if bad or not rank_by:
        raise InputError(f"rank by organs of the model ({', '.join(ORGANS)}), not {', '.join(bad) or 'none'}")
    case, model, step = _planning_model(a)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="plan-planes-") as work:
        rows = plane_sweep_task(_simulation_case(a, case, work), a.truth_seed, "breathing", families, a.positions,
                                truth_cell_mm=a.truth_cell_mm, particle_step=step, methods=("initial", "copy"))
    wall = time.perf_counter() - t0
    good = [r for r in rows if not r.get("failure")]
    if not good:
        raise SimulationError("no placement could be simulated: " + "; ".join(sorted({r["failure"] for r in rows})))
    score = np.array([np.mean([r[f"copy_{o}_mm"] for o in rank_by]) for r in good])
    order = np.argsort(score, kind="stable")
    ranked = [good[i] for i in order]
    motion = {o: good[0][f"initial_{o}_mm"] for o in ORGANS}
    head = f"{'#':>3}  {'planes':<24}" + "".join(f"{o[:11]:>12}" for o in ORGANS)
    lines = [f"plane placements for the {'+'.join(rank_by)}, best first: each organ's mean error (mm) copying the planes' "
             f"motion, on a finite-element breathing truth of this scan (truth seed {a.truth_seed}; the organs move "
             + ", ".join(f"{o} {motion[o]:.1f}" for o in ORGANS) + " mm)", head]
    for i, r in enumerate(ranked[:a.top]):
        lines.append(f"{i + 1:>3}  {r['planes']:<24}" + "".join(f"{r[f'copy_{o}_mm']:>12.2f}" for o in ORGANS))
    rules = {}
    for family in families:
        fam = [i for i, r in enumerate(ranked) if r["family"] == family]
        if not fam:
            continue
        rule = next(i for i in fam if is_rule(ranked[i]))
        rules[family] = {"rank": rule + 1, "planes": ranked[rule]["planes"]}
        lines.append(f"{family}: best #{fam[0] + 1} {ranked[fam[0]]['planes']} ({score[order][fam[0]]:.2f} mm); the rule without "
                     f"a model (most pancreas on each plane) {ranked[rule]['planes']} ranks #{rule + 1} "
                     f"({score[order][rule]:.2f} mm)")
    failed = len(rows) - len(good)
    lines.append(f"{len(good)} placements simulated in {wall:.0f} s" + (f"; {failed} failed" if failed else ""))
    print("\n".join(lines))
    if a.picture:
        entries = [(Placement(r["family"], tuple(parse_slices(r["planes"]))), None, {}) for r in ranked]
        draw_placements(model, entries, a.picture, top=min(3, a.top))
        print(f"picture: {a.picture}")
    if a.json:
        doc = {"units": "mean error of each organ (mm) copying the planes' true in-plane motion, on a finite-element "
                        "breathing truth of the planning scan; slice indices of the planning scan",
               "truth_seed": a.truth_seed, "rank_by": list(rank_by), "simulation_s": wall, "motion_mm": motion,
               "placements": [{"rank": i + 1, "family": r["family"], "planes": r["planes"],
                               "simulated_error_mm": {o: r[f"copy_{o}_mm"] for o in ORGANS}} for i, r in enumerate(ranked)],
               "rule": rules}
        write_json_atomic(a.json, doc)
        print(f"ranking: {a.json}")
    return 0


def cmd_train_planes(a) -> int:
    """``warpmpm train-planes``: the placement model from plane-sweep CSVs, reported split by case."""
    from ..experiment.train_planes import train_planes

    from ..experiment.io import check_output_path

    for path, option in ((a.out, "--out"), (a.report, "--report")):
        if path:
            check_output_path(path, option, inputs=[("CSV", p) for p in a.csv])
    test_cases = [c for c in a.test_cases.split(",") if c] if a.test_cases else None
    train_planes(a.csv, test_cases=test_cases, method=a.method, out=a.out, report=a.report, storage=a.storage,
                 max_trials=a.max_trials, patience=a.patience, progress=lambda m: print(m, file=sys.stdout))
    return 0

