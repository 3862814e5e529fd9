"""Study (2026-12-02; answer in benchmarks/studies/README.md). How far below ``propagate`` can the cine tracker's physics get, given a perfect slice registration? (issue 15)

The tracker ties ``propagate`` on the MR cine series (docs/results.md). This asks whether that is the registration's fault
or the information's: for each frame of a synthetic series (``benchmarks/track_series.py`` makes them), from the
planning state and with the **true** in-plane motion of every particle the frame's plane holds (what a perfect 2D
deformable registration would measure; the through-plane part is not given, as no 2D frame gives it):

- ``propagate``: each organ's in-plane affine fitted to its particles on the plane, copied to the whole organ
  (organs off the plane take the whole plane's): the tracker's baseline with a perfect organ-aware affine registration;
- ``estimate``: the physics from that prediction, every particle on the plane driven onto its true in-plane
  position (in-plane drive), to the settled equilibrium (the quasi-static solver, as the tracker's ``auto`` does);
- ``estimate, noise S mm``: the same with a smooth Gaussian random error of S mm (standard deviation of each in-plane
  component, correlation length ``--noise-length-mm`` in the plane, 0: independent per particle) on the driven
  particles' targets, and the affines fitted to those same noisy targets: how accurate a deformable registration
  would have to be for the physics to keep its margin over copying its affines.

Pancreas error (mean over its particles, mm), mean over the chosen frames; ``initial`` is no motion.

    python benchmarks/studies/track_ceiling.py                              # sagittal seeds 0-3, frames 5, 11, 17
    python benchmarks/studies/track_ceiling.py --series sagittal_s0_f20 --frames 19 --noise 0,0.25,0.5,1

Needs the series under ``--work`` (made by ``track_series.py``) and ``../shared/data/totalseg_mr`` (skipped with a
message if absent). Raw numbers: ``benchmarks/studies/results/track_ceiling.json``.
"""

import argparse
import json
import os
import sys
import time
import warnings

import numpy as np


from warpmpm.experiment import raw_numbers as raw

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
DATA = os.path.join(ROOT, "..", "shared", "data", "totalseg_mr")


def organ_affine_copy(model, before, after, on, frame):
    """Every particle moved by its organ's in-plane affine fitted to ``after`` on the plane (the whole plane's for
    organs with fewer than 10 particles there); the through-plane coordinate kept."""
    from warpmpm.slices import InPlaneAffine

    axes = (frame.e_u, frame.e_v, frame.centre_mm)
    whole = InPlaneAffine.fit(before[on], after[on], *axes)
    out = before.copy()
    for k in range(len(model.organs)):
        members = model.organ_index == k
        own = on[model.organ_index[on] == k]
        affine = InPlaneAffine.fit(before[own], after[own], *axes) if len(own) >= 10 else whole
        out[members] = affine.apply(before[members], *axes)
    return out


def smooth_noise(rng, uv, sd_mm, length_mm, features=256):
    """(N, 2) Gaussian random in-plane errors at in-plane points ``uv`` (N, 2, mm): standard deviation ``sd_mm`` per
    component, squared-exponential correlation of length ``length_mm`` (random Fourier features); 0: independent."""
    if length_mm <= 0:
        return rng.normal(0.0, sd_mm, (len(uv), 2))
    w = rng.normal(0.0, 1.0 / length_mm, (features, 2))
    phase = rng.uniform(0.0, 2 * np.pi, (features, 2))
    amp = rng.normal(0.0, 1.0, (features, 2))
    arg = uv @ w.T  # (N, features)
    return sd_mm * np.sqrt(2.0 / features) * np.stack([(np.cos(arg + phase[:, c]) * amp[:, c]).sum(1) for c in range(2)], axis=1)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--series", default="sagittal_s0_f20,sagittal_s1_f20,sagittal_s2_f20,sagittal_s3_f20")
    p.add_argument("--frames", default=None, help="frame numbers (default: 5, 11, 17)")
    p.add_argument("--noise", default="0,0.5", help="target noise levels, mm (0: the true in-plane motion)")
    p.add_argument("--noise-length-mm", type=float, default=10.0, help="correlation length of the target noise (0: independent)")
    p.add_argument("--newton", type=int, default=12, help="Newton iterations at most per solve (a settled frame took 7-11)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--work", default=os.path.join(ROOT, "runs", "track_series"))
    a = p.parse_args(argv)
    if not os.path.exists(os.path.join(DATA, "image.nii.gz")):
        print(f"skipped: the MR sample is not at {DATA}")
        return 0
    import warp as wp

    wp.config.quiet = True
    from warpmpm.cine import read_cine
    from warpmpm.driving import SliceDrivenEstimator
    from warpmpm.images import load_case
    from warpmpm.model import build_model
    from warpmpm.solvers import QuasiStaticConfig, SolverConfig

    warnings.simplefilter("ignore")
    case = load_case(os.path.join(DATA, "labels.nii.gz"), os.path.join(DATA, "image.nii.gz"), preset="totalseg_mr")
    try:
        noise = [float(s) for s in a.noise.split(",")]
        wanted = [int(k) for k in a.frames.split(",")] if a.frames else None
    except ValueError as e:
        p.error(f"--noise takes numbers (mm) and --frames whole frame numbers, comma-separated: {e}")
    if not all(np.isfinite(s) and s >= 0 for s in noise):
        p.error(f"--noise levels must be finite and >= 0 mm, got {a.noise}")
    rng = np.random.default_rng(a.seed)
    rows = []
    print("| series | frame | initial | propagate (perfect organ affines) | estimate (true in-plane targets) | "
          + " | ".join(f"propagate / estimate, noise {s:g} mm" for s in noise if s > 0) + " | settled |")
    print("|---" * (6 + sum(s > 0 for s in noise)) + "|")
    for name in a.series.split(","):
        truth_dir = os.path.join(a.work, name, "truth")
        if not os.path.exists(os.path.join(truth_dir, "positions.npz")):
            print(f"| {name} | skipped: no series at {truth_dir} (run benchmarks/track_series.py first) |")
            continue
        tr = np.load(os.path.join(truth_dir, "positions.npz"))
        with open(os.path.join(truth_dir, "series.json")) as f:
            series = json.load(f)
        frames = read_cine(os.path.join(a.work, name, "cine"))
        model = build_model(case, tuple(str(o) for o in tr["organs"]), sampling_step=int(series["particle_step"]))
        if not np.allclose(model.positions_mm, tr["planning_mm"], atol=0.01):
            print(f"| {name} | skipped: the truth was built on another particle model |")
            continue
        P0 = model.positions_mm
        pan = model.organ_slice("pancreas")
        picked = wanted if wanted is not None else list(range(5, len(frames), 6))
        if any(k < 0 or k >= min(len(frames), len(tr["truth_mm"])) for k in picked):
            p.error(f"--frames {a.frames}: {name} has frames 0-{min(len(frames), len(tr['truth_mm'])) - 1}")
        for k in picked:
            T, frame = tr["truth_mm"][k], frames[k]
            on = np.nonzero(np.abs(frame.distance_mm(T)) <= frame.thickness_mm / 2)[0]  # on the plane when imaged
            err = lambda X: float(np.linalg.norm(X[pan] - T[pan], axis=1).mean())  # noqa: E731
            row = {"series": name, "frame": k, "plane": frame.plane, "driven": len(on), "initial_mm": err(P0)}
            for s in noise:
                seen = T.copy()
                if s > 0:
                    e = smooth_noise(rng, frame.in_plane(T[on]), s, a.noise_length_mm)
                    seen[on] += e[:, :1] * frame.e_u + e[:, 1:] * frame.e_v
                prop = organ_affine_copy(model, P0, seen, on, frame)
                targets = prop[on] + (frame.in_plane(seen[on]) - frame.in_plane(prop[on])) @ np.stack([frame.e_u, frame.e_v])
                est = SliceDrivenEstimator(model, driven=on, solver_config=SolverConfig(device="cpu", method="quasistatic",
                                                                        quasistatic=QuasiStaticConfig(max_newton_iterations=a.newton)),
                                           extra_points_mm=np.vstack([P0 - 20.0, P0 + 20.0]))
                est.move_to(prop)
                t0 = time.perf_counter()
                r = est.estimate(targets, axes=np.tile(frame.projector, (len(on), 1, 1)))
                row[f"noise_{s:g}"] = {"propagate_mm": err(prop), "estimate_mm": err(r.positions_mm), "settled": bool(r.settled),
                                       "iterations": int(r.steps), "wall_s": time.perf_counter() - t0}
            rows.append(row)
            n0 = row[f"noise_{noise[0]:g}"]
            rest = " | ".join(f"{row[f'noise_{s:g}']['propagate_mm']:.3f} / {row[f'noise_{s:g}']['estimate_mm']:.3f}" for s in noise[1:])
            print(f"| {name} | {k} | {row['initial_mm']:.3f} | {n0['propagate_mm']:.3f} | {n0['estimate_mm']:.3f} | {rest} | "
                  f"{sum(row[f'noise_{s:g}']['settled'] for s in noise)} of {len(noise)} |", flush=True)
    if rows:
        print("\nmean over frames:")
        for s in noise:
            pm = np.mean([r[f"noise_{s:g}"]["propagate_mm"] for r in rows])
            em = np.mean([r[f"noise_{s:g}"]["estimate_mm"] for r in rows])
            better = sum(r[f"noise_{s:g}"]["estimate_mm"] < r[f"noise_{s:g}"]["propagate_mm"] for r in rows)
            print(f"  noise {s:g} mm: propagate {pm:.3f}, estimate {em:.3f} ({100 * (em / pm - 1):+.1f} %, {better} of {len(rows)} "
                  f"frames better); initial {np.mean([r['initial_mm'] for r in rows]):.3f}")
        raw.save(__file__, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
