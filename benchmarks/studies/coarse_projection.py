"""Study (2026-12-02; answer in benchmarks/studies/README.md). Is the motion that keeps a settled frame from settling in the rigid-mode acceleration's coarse space? (issue 17)

    python benchmarks/studies/coarse_projection.py [--step 1000] [--window 100] [--eigen 4]

The load of ``settling.py`` (the default phantom's mid-pancreas axial slice scaled 2 % in plane, all four organs,
settled mode with the default rigid-mode acceleration). At ``--step`` the particles' move over the next ``--window``
steps is taken, moved to the grid nodes (mass-weighted, the MPM's own B-spline weights) and projected on the coarse
space a build of the acceleration at that state makes (``RigidModeAccelerator.build``: each cube's motions on the
nodes, ``E = Z^T K Z``, ``M_c = Z^T M Z``, the boosts). Printed: how much of the move (mass norm) the projection holds,
the coarse model's
frequency of it (``omega dt``), the coarse eigenmodes it lies in with their boosts, the coarse target, and the adaptive
damping's reading of the motion the body actually makes (critical damping ``gamma = 2 omega``); and the pace the
preconditioned operator gives that motion, ``omega^2 = -u.M dv / u.M u`` with ``dv = (M^-1 + Z B Z^T) f`` and ``f = -K u``
(``K``: the small-strain stiffness and the drive's spring at that state, the quasi-static solver's operator), beside
the same without the coarse correction. With ``--eigen N``: the N slowest modes of the accelerated relaxation itself
(LOBPCG on ``K v = lambda P^-1 v``, ``P = M^-1 + Z B Z^T`` the step's preconditioner at that state, ``P^-1`` by Woodbury
over the boosted coarse modes), their overlap with the move, how much of each lies in the coarse space and in the
boosted modes (mass norm), and its pace without the correction. Raw numbers: ``benchmarks/studies/results/coarse_projection.json``.
"""

import argparse
import sys
import warnings

import numpy as np


from warpmpm.experiment import raw_numbers as raw
import warp as wp

from warpmpm import InPlaneAffine, build_model, make_phantom
from warpmpm.driving import ConvergenceConfig, SliceDrivenEstimator
from warpmpm.solvers.quasistatic import apply_stiffness, grid_view
from warpmpm.solvers.coarse_space import basis, stencils
from warpmpm.solvers.rigid_modes import RigidModeAccelerator
from warpmpm.slices import DrivingSlice
from warpmpm.solvers import SolverConfig
from warpmpm.targets import affine_targets


def coarse_basis(c: dict, dx: float, grid_shape, affine: bool) -> np.ndarray:
    """The coarse space ``Z`` of a build (``RigidModeAccelerator.coarse``) as a dense (3 x active nodes, modes) matrix:
    each group's share of each node times its motion there, as the restriction and prolongation kernels apply it."""
    a_c, A_c = basis(affine)
    S = a_c.shape[0]
    nodes = c["nodes"]
    ny, nz = grid_shape[1], grid_shape[2]
    X = np.stack([nodes // (ny * nz), (nodes // nz) % ny, nodes % nz], axis=1) * dx
    Z = np.zeros((nodes.size, 3, c["E"].shape[0]))
    for q in range(c["node_group"].shape[1]):
        sh, g = c["node_share"][:, q], c["node_group"][:, q]
        ok = np.nonzero(sh > 0)[0]
        y = (X[ok] - c["centre"][g[ok]]) / c["radius"][g[ok], None]
        zv = sh[ok, None, None] * (a_c[None] + np.einsum("cij,nj->nci", A_c, y))
        for k in range(S):
            Z[ok, :, g[ok] * S + k] += zv[:, k, :]
    return Z.reshape(3 * nodes.size, -1)


def stiffness_operator(est, x0_m: np.ndarray, nodes: np.ndarray):
    """``v -> K v`` on the active ``nodes`` (3 values a node; one column or several): the small-strain stiffness at
    positions ``x0_m`` plus the drive's spring, the quasi-static solver's operator (:func:`apply_stiffness`)."""
    mp, d = est.mpm, est.mpm.device
    gs = mp.grid_shape
    nn, na = int(np.prod(gs)), nodes.size
    mass = mp.mass_kg.astype(np.float64)
    pen_k = np.zeros(mp.n, np.float32)
    proj = np.zeros((mp.n, 3, 3), np.float32)
    pen_k[est.driven] = est.gains.kp_per_s2 * mass[est.driven]
    proj[est.driven] = est.driven_axes()
    xw = wp.array(x0_m.astype(np.float32), dtype=wp.vec3, device=d)
    pk, pw = wp.array(pen_k, dtype=float, device=d), wp.array(proj, dtype=wp.mat33, device=d)
    vin, out = wp.zeros(nn, dtype=wp.vec3, device=d), wp.zeros(nn, dtype=wp.vec3, device=d)
    full = np.zeros((nn, 3))

    def kmul(v):
        v2 = v.reshape(3 * na, -1)
        res = np.empty_like(v2)
        for j in range(v2.shape[1]):
            full[:] = 0.0
            full[nodes] = v2[:, j].reshape(na, 3)
            vin.assign(full.astype(np.float32))
            out.zero_()
            wp.launch(apply_stiffness, mp.n, [xw, mp.vol0, mp.mu, mp.lam, pk, pw, mp.dx_mm * 1e-3, gs[1], gs[2], grid_view(vin, gs[1], gs[2]), 0, grid_view(out, gs[1], gs[2])], device=d)
            res[:, j] = out.numpy()[nodes].astype(np.float64).ravel()
        return res.reshape(v.shape)

    return kmul


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--step", type=int, default=1000, help="step at which the move is taken (after the slice has arrived)")
    p.add_argument("--window", type=int, default=100, help="steps the move spans (a multiple of the estimator's batch)")
    p.add_argument("--eigen", type=int, default=0, help="also the N slowest modes of the accelerated relaxation (LOBPCG; 0: none)")
    a = p.parse_args(argv)
    if a.eigen < 0 or a.eigen > 12:
        p.error("--eigen must be 0-12")
    if a.step < 300 or a.window < 50:
        p.error("--step must be at least 300 (the coarse level starts when the slice has arrived) and --window at least 50")
    wp.config.quiet = True
    warnings.simplefilter("ignore")
    case = make_phantom()
    m = build_model(case, "psdl", sampling_step=2)
    k = int(np.median(m.voxel_ijk[m.organ_slice("pancreas"), 2]))
    sl = [DrivingSlice("axial", k)]
    _, tg = affine_targets(m, m.positions_mm, sl, [InPlaneAffine(1.02 * np.eye(2))], case.geometry.center_mm())
    keep = {}

    def at(est, s, rel, rms):
        if s == a.step and est.accelerator is not None and est.accelerator.built:
            # the coarse level as a build at this state makes it (a second accelerator: the running one is left alone)
            acc = RigidModeAccelerator(est.mpm, aggregate_mm=est.mpm.config.acceleration.aggregate_mm, modes=est.mpm.config.acceleration.basis)
            acc.build(est.state, est.driven, est.driven_axes(), est.gains.kp_per_s2)
            keep.update(x0=est.state.x.numpy().astype(np.float64), damping_per_s=est.solver.damping_per_s, acc=acc)
        if s == a.step + a.window and "x0" in keep:
            keep["x1"] = est.state.x.numpy().astype(np.float64)

    est = SliceDrivenEstimator(m, sl, solver_config=SolverConfig(), callback=at,
                               convergence=ConvergenceConfig(wait_settled=True, max_steps=a.step + a.window))
    est.estimate(tg)
    if "x1" not in keep:
        print(f"no coarse level ran at step {a.step} (settled before, or not started): nothing to project")
        return 1
    acc, x0 = keep["acc"], keep["x0"]
    c = acc.coarse
    dt, dx = est.mpm.dt_s, est.mpm.dx_mm * 1e-3
    nodes, node_mass = c["nodes"], c["node_mass"]
    mw = np.repeat(node_mass, 3)
    # the move on the active nodes (mass-weighted, the MPM's B-spline weights)
    move = keep["x1"] - x0
    mass = est.mpm.mass_kg.astype(np.float64)
    flat, w, _ = stencils(wp.array(x0.astype(np.float32), dtype=wp.vec3, device=est.mpm.device), dx, est.mpm.grid_shape, est.mpm.device)
    nn = int(np.prod(est.mpm.grid_shape))
    mom = np.zeros((nn, 3))
    mn = np.zeros(nn)
    for comp in range(3):
        np.add.at(mom[:, comp], flat.ravel(), (w * (mass * move[:, comp])[:, None]).ravel())
    np.add.at(mn, flat.ravel(), (w * mass[:, None]).ravel())
    u = (mom[nodes] / np.maximum(mn[nodes], 1e-30)[:, None]).ravel()
    Z = coarse_basis(c, dx, est.mpm.grid_shape, acc.affine)
    kmul = stiffness_operator(est, x0, nodes)
    Mc, E, Phi = c["Mc"], c["E"], acc.mode_shapes
    # its projection on the coarse space and the coarse eigenmodes it lies in (Phi^T M_c Phi = I)
    yc = np.linalg.solve(Mc, Z.T @ (mw * u))
    umu = float(u @ (mw * u))
    held = float(yc @ Mc @ yc / umu)
    omega_c = float(np.sqrt(max(yc @ E @ yc / (yc @ Mc @ yc), 0.0)))
    coef = Phi.T @ (Mc @ yc)
    weight = coef**2 / float((coef**2).sum())
    modes = [{"omega_dt": float(acc.frequencies_per_s[j] * dt), "weight": float(weight[j]), "boost": float(acc.boosts[j])}
             for j in np.argsort(-weight)[:6]]
    # the step's operator along the move: f = -K u, dv = M^-1 f + Z B Z^T f
    B = Phi @ np.diag(acc.boosts - 1.0) @ Phi.T
    f = -kmul(u)
    plain = -float(u @ f) / umu
    boosted = -float(u @ (f + mw * (Z @ (B @ (Z.T @ f))))) / umu
    res = {"step": a.step, "window": a.window, "move_rms_mm": float(1e3 * np.sqrt((move**2).sum(1).mean())), "held_by_coarse_space": held,
           "coarse_omega_dt": omega_c * dt, "target_omega_dt": acc.target_per_s * dt,
           "body_omega_dt_from_damping": keep["damping_per_s"] * dt / 2.0, "modes": modes,
           "operator_omega_dt_without_coarse": float(np.sqrt(max(plain, 0.0)) * dt),
           "operator_omega_dt_with_coarse": float(np.sqrt(max(boosted, 0.0)) * dt)}
    print(f"move over steps {a.step}-{a.step + a.window}: {res['move_rms_mm']:.4f} mm RMS")
    print(f"held by the coarse space (mass norm): {held:.4f}")
    print(f"omega dt: coarse model of the move {res['coarse_omega_dt']:.5f}, coarse target {res['target_omega_dt']:.5f}, "
          f"the body's motion by the adaptive damping {res['body_omega_dt_from_damping']:.5f}")
    print(f"the operator along the move: omega dt {res['operator_omega_dt_without_coarse']:.5f} without the coarse correction, "
          f"{res['operator_omega_dt_with_coarse']:.5f} with it")
    print("| coarse eigenmode omega dt | share of the move | boost |")
    print("|---|---|---|")
    for md in modes:
        print(f"| {md['omega_dt']:.5f} | {md['weight']:.3f} | {md['boost']:.1f} |")
    if a.eigen:
        res["slowest_modes"] = slowest_modes(kmul, Z, mw, Phi, acc.boosts, u, dt, a.eigen)
        print("| accelerated mode omega dt | overlap with the move | in the coarse space | in the boosted modes | "
              "pace without the correction | mass share of its 50 largest nodes |")
        print("|---|---|---|---|---|---|")
        for md in res["slowest_modes"]:
            print(f"| {md['omega_dt']:.5f} | {md['overlap']:.3f} | {md['in_coarse']:.3f} | {md['in_boosted']:.3f} | "
                  f"{md['plain_omega_dt']:.5f} | {md['top50']:.3f} |")
    raw.save(__file__, res)
    return 0


def slowest_modes(kmul, Z, mw, Phi, boosts, u, dt, count):
    """The ``count`` slowest modes of the relaxation with the coarse correction (``K v = lambda P^-1 v``,
    ``P = M^-1 + Z B Z^T``; ``P^-1 = M - M W diag((beta - 1) / beta) W^T M`` with ``W = Z Phi_b`` over the boosted modes,
    ``W^T M W = I``), each with its overlap with the move ``u`` and where its mass lies."""
    from scipy.sparse.linalg import LinearOperator, lobpcg

    b = boosts > 1.0
    W = Z @ Phi[:, b]
    beta = boosts[b]
    keepf = (beta - 1.0) / beta

    def pinv(v):
        v2 = v.reshape(mw.size, -1)
        mv = mw[:, None] * v2
        return (mv - mw[:, None] * (W @ (keepf[:, None] * (W.T @ mv)))).reshape(v.shape)

    def pmul(v):
        v2 = v.reshape(mw.size, -1)
        return (v2 / mw[:, None] + W @ ((beta - 1.0)[:, None] * (W.T @ v2))).reshape(v.shape)

    n3 = mw.size
    A, Bop, T = (LinearOperator((n3, n3), matvec=f, matmat=f, dtype=np.float64) for f in (kmul, pinv, pmul))
    rng = np.random.default_rng(0)
    X0 = np.column_stack([u] + [rng.standard_normal(n3) for _ in range(count - 1)])
    vals, vecs = lobpcg(A, X0, B=Bop, M=T, largest=False, maxiter=300, tol=1e-6)
    mc_inv = np.linalg.inv(Z.T @ (mw[:, None] * Z))
    uq = u / np.sqrt(u @ pinv(u))
    modes = []
    for j in np.argsort(vals):
        v = vecs[:, j] / np.sqrt(vecs[:, j] @ pinv(vecs[:, j]))
        vmv = float(v @ (mw * v))
        ztmv, wtmv = Z.T @ (mw * v), W.T @ (mw * v)
        amp = np.sort((mw * v * v).reshape(-1, 3).sum(1))[::-1]
        modes.append({"omega_dt": float(np.sqrt(max(vals[j], 0.0)) * dt), "overlap": float(abs(v @ pinv(uq))),
                      "in_coarse": float(ztmv @ mc_inv @ ztmv / vmv), "in_boosted": float(wtmv @ wtmv / vmv),
                      "plain_omega_dt": float(np.sqrt(max(v @ kmul(v) / vmv, 0.0)) * dt), "top50": float(amp[:50].sum() / amp.sum())})
    return modes


if __name__ == "__main__":
    sys.exit(main())
