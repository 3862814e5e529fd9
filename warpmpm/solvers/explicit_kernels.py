"""Warp kernels of one explicit MLS-MPM (APIC) step with quadratic B-splines.

Units inside the kernels are SI: positions in metres *relative to the grid origin*, velocities
in m/s, masses in kg, volumes in m^3, stresses in Pa, forces in N, time in s. The solver converts
from and to the public millimetre world coordinates.

The step, for particles p and grid nodes i:

1. ``p2g``: the Kirchhoff stress of the fixed-corotated model (Stomakhin et al. 2012),
   ``tau = 2 mu (F - R) F^T + lambda (J - 1) J I``, R = U V^T of the SVD of F, computed by a
   polar-decomposition Newton iteration (4x cheaper on the CPU) with ``wp.svd3`` as the fallback;
   then mass, APIC momentum ``w (m v + (m C - dt V0 4/dx^2 tau) (x_i - x_p))`` and the external
   (driving) force ``w dt f_p``, scattered with atomics. Stress and scatter are one pass: the stress
   is never written to memory and read back (72 bytes a particle a step less).
2. ``grid_update``: velocity = momentum / mass, damping, wall conditions; it zeroes the mass and
   momentum it has read (no separate clearing pass). On the CPU ``grid_update_blocks`` does the same over
   the blocks of nodes that hold mass only (P2G stamps them), with the dense update's result.
3. ``g2p``: particle velocity, affine C, position, ``F <- (I + dt C) F``, and the guards that keep
   every particle inside the grid and flag non-finite values.
4. With adaptive damping (the settled mode), ``stiffness_rayleigh`` and the one-thread ``adapt_damping``
   set the next step's velocity factor on the device (``damping`` is a one-element array, so a captured
   graph replays it without a host read-back).
"""

from typing import Any

import warp as wp

__all__ = ["STATUS_OK", "STATUS_NONFINITE", "STATUS_LEFT_GRID", "BLOCK", "bspline_weights", "base_node", "cofactor",
           "polar_rotation", "offset_in_stencil", "stencil", "fixed_corotated_kirchhoff", "stress_impulse",
           "apic_stress_affine", "scatter_linear", "p2g", "bspline_slopes", "p2g_fields", "slip_walls",
           "grid_update_fields", "update_node", "grid_update", "grid_update_blocks", "is_finite_vec",
           "gather_velocity", "g2p", "stiffness_rayleigh", "adapt_damping"]

# Forward kernels only (nothing here is differentiated): no adjoint code to build, which halves the first run's
# compile (CPU 55 -> 22 s for the package's four kernel modules; CUDA PTX 91 -> 18 s an architecture).
wp.set_module_options({"enable_backward": False})

#: flag codes written to the solver's status array
STATUS_OK = 0
STATUS_NONFINITE = 1
STATUS_LEFT_GRID = 2

#: nodes along each axis of a block of the sparse grid update's activity flags (:func:`grid_update_blocks`)
BLOCK = wp.constant(4)


@wp.func
def bspline_weights(fx: wp.vec3, axis: int):
    """Quadratic B-spline weights of the 3 nodes along one axis for fractional offset ``fx``."""
    f = fx[axis]
    return wp.vec3(0.5 * (1.5 - f) * (1.5 - f), 0.75 - (f - 1.0) * (f - 1.0), 0.5 * (f - 0.5) * (f - 0.5))


@wp.func
def base_node(x: wp.vec3, inv_dx: float):
    """Index of the first of the 3x3x3 nodes a particle at grid-local ``x`` (m) touches."""
    return wp.vec3i(int(x[0] * inv_dx - 0.5), int(x[1] * inv_dx - 0.5), int(x[2] * inv_dx - 0.5))


@wp.func
def cofactor(X: wp.mat33):
    """The cofactor matrix of X: ``det(X) X^-T``."""
    return wp.mat33(X[1, 1] * X[2, 2] - X[1, 2] * X[2, 1], X[1, 2] * X[2, 0] - X[1, 0] * X[2, 2], X[1, 0] * X[2, 1] - X[1, 1] * X[2, 0],
                    X[0, 2] * X[2, 1] - X[0, 1] * X[2, 2], X[0, 0] * X[2, 2] - X[0, 2] * X[2, 0], X[0, 1] * X[2, 0] - X[0, 0] * X[2, 1],
                    X[0, 1] * X[1, 2] - X[0, 2] * X[1, 1], X[0, 2] * X[1, 0] - X[0, 0] * X[1, 2], X[0, 0] * X[1, 1] - X[0, 1] * X[1, 0])


@wp.func
def polar_rotation(F: wp.mat33):
    """Rotation R of the polar decomposition F = R S.

    Scaled Newton iteration ``X <- (g X + (g X)^-T) / 2``, ``g = |det X|^(-1/3)``, which converges
    quadratically to ``U V^T`` of the SVD for det F > 0. Falls back to ``wp.svd3`` when F is nearly
    inverted (det F < 0.05) or the iteration has not converged after 12 steps, so the result equals
    the SVD-based rotation of Stomakhin et al. (2012) in every case.

    ``X^-T`` comes from the cofactors, whose first row also gives ``det X`` (one determinant an iteration);
    ``g`` is left at 1 once ``det X`` is within 1e-3 of 1 (it would change X by under 3e-4 there, and its
    ``pow`` was the iteration's dearest operation); the loop stops when converged. Measured on 113k particles
    (one thread): 17.9 -> 10.3 ms for 1 % strains, 20.8 -> 15.9 ms for 5 % strains with any rotation, the same
    rotation within 2.4e-7.

    Converged: near R the iteration converges quadratically (``X = R (I + E)`` -> ``R (I + E^2 / 2)``), so a step of
    size ``err`` (max row sum of ``Y - X``) leaves an error of about ``err^2 / 2``; the loop stops once that is below
    float32 resolution (err < 3e-4) instead of waiting for a step below 1e-6, which cost one more iteration. Measured
    on 113k rotated symmetric strains, one thread, against the 1e-6 rule in the same process: the same largest
    difference from the float64 SVD rotation (1.3-1.6e-7 at strains 1e-4 to 0.3), 0.60x the time at 1e-4, 0.77x at
    1e-2, 0.98-1.0x at 3-5 %.

    The scale ``g`` (any g > 0 keeps the limit: it only speeds convergence) is a second-order Taylor expansion of
    ``|det X|^(-1/3)`` when det X is within 20 % of 1 (0.2 % off there) instead of a ``pow``: P2G 0.91x the time on
    the default phantom's paper frame and on the 97k-particle compressed cube of ``benchmarks/solver_step.py`` (one
    thread, alternated in one process), the same rotations (``tests/test_solver.py``).
    """
    X = F
    done = int(0)
    if wp.determinant(F) > 0.05:
        for it in range(12):
            Cf = cofactor(X)
            det = X[0, 0] * Cf[0, 0] + X[0, 1] * Cf[0, 1] + X[0, 2] * Cf[0, 2]
            g = float(1.0)
            e = det - 1.0
            if wp.abs(e) > 1.0e-3:
                if wp.abs(e) < 0.2:  # |det|^(-1/3) to 0.2 % (any g > 0 keeps the limit: it only speeds convergence)
                    g = 1.0 - e * (1.0 / 3.0) + (2.0 / 9.0) * e * e
                else:
                    g = wp.pow(wp.abs(det), -1.0 / 3.0)
            Y = 0.5 * (g * X + (1.0 / (g * det)) * Cf)
            D = Y - X
            err = wp.max(wp.max(wp.abs(D[0, 0]) + wp.abs(D[0, 1]) + wp.abs(D[0, 2]), wp.abs(D[1, 0]) + wp.abs(D[1, 1]) + wp.abs(D[1, 2])),
                         wp.abs(D[2, 0]) + wp.abs(D[2, 1]) + wp.abs(D[2, 2]))
            X = Y
            if err < 3.0e-4:  # quadratic convergence: the error left is ~err^2 / 2 < 4.5e-8, float32 resolution
                done = 1
                break
    if done == 0:
        U = wp.mat33()
        sig = wp.vec3()
        V = wp.mat33()
        wp.svd3(F, U, sig, V)
        X = U * wp.transpose(V)
    return X


@wp.func
def offset_in_stencil(x: wp.vec3, inv_dx: float, base: wp.vec3i):
    """Particle position relative to its first stencil node, in cells (each component in [0.5, 1.5))."""
    return wp.vec3(x[0] * inv_dx - float(base[0]), x[1] * inv_dx - float(base[1]), x[2] * inv_dx - float(base[2]))


@wp.func
def stencil(x: wp.vec3, inv_dx: float):
    """A particle's 3x3x3 stencil: its first node, its offset from that node in cells, and the quadratic
    B-spline weights along x, y and z."""
    base = base_node(x, inv_dx)
    fx = offset_in_stencil(x, inv_dx, base)
    return base, fx, bspline_weights(fx, 0), bspline_weights(fx, 1), bspline_weights(fx, 2)


@wp.func
def fixed_corotated_kirchhoff(F: wp.mat33, mu: float, lam: float):
    """Kirchhoff stress tau = P F^T of the fixed-corotated model (Pa)."""
    J = wp.determinant(F)
    I = wp.identity(n=3, dtype=float)
    D = F - I
    small = wp.max(wp.max(wp.max(wp.abs(D[0, 0]), wp.abs(D[0, 1])), wp.max(wp.abs(D[0, 2]), wp.abs(D[1, 0]))),
                   wp.max(wp.max(wp.abs(D[1, 1]), wp.abs(D[1, 2])), wp.max(wp.max(wp.abs(D[2, 0]), wp.abs(D[2, 1])), wp.abs(D[2, 2]))))
    if small < 1.0e-5:
        # Linearised model near the identity: exact zero at rest, error O(|F - I|^2 mu).
        return mu * (D + wp.transpose(D)) + lam * (D[0, 0] + D[1, 1] + D[2, 2]) * I
    R = polar_rotation(F)
    return 2.0 * mu * (F - R) * wp.transpose(F) + lam * (J - 1.0) * J * I


@wp.func
def stress_impulse(F: wp.mat33, V0: float, mu: float, lam: float, dt: float, inv_dx: float):
    """The stress part of what a particle scatters with its offset to each node (MLS-MPM):
    ``-dt V0 4/dx^2 tau``, tau the fixed-corotated Kirchhoff stress of F."""
    return -(dt * V0 * 4.0 * inv_dx * inv_dx) * fixed_corotated_kirchhoff(F, mu, lam)


@wp.func
def apic_stress_affine(F: wp.mat33, C: wp.mat33, m: float, V0: float, mu: float, lam: float, dt: float, inv_dx: float):
    """The matrix a particle scatters with its offset to each node: APIC momentum ``m C`` plus the
    :func:`stress_impulse`."""
    return m * C + stress_impulse(F, V0, mu, lam, dt, inv_dx)


@wp.func
def scatter_linear(out: wp.array(dtype=wp.vec3, ndim=3), i0: int, base: wp.vec3i, wx: wp.vec3, wy: wp.vec3, wz: wp.vec3, u0: wp.vec3,
                   A0: wp.vec3, A1: wp.vec3, A2: wp.vec3):
    """Add ``w_abc (u0 + a A0 + b A1 + c A2)`` to node ``(i0 + base[0] + a, base[1] + b, base[2] + c)`` of a particle's
    3x3x3 stencil, the sum built up along the loops (``w (u + M (abc - fx) dx)`` with ``u0 = u - M fx dx`` and ``A_k``
    the k-th column of ``M dx``: no matrix-vector product a node)."""
    for a in range(3):
        ua = u0 + float(a) * A0
        for b in range(3):
            uab = ua + float(b) * A1
            wab = wx[a] * wy[b]
            for c in range(3):
                wp.atomic_add(out, i0 + base[0] + a, base[1] + b, base[2] + c, (wab * wz[c]) * (uab + float(c) * A2))


@wp.kernel
def p2g(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    f_ext: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    vol0: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    dx: float,
    dt: float,
    part_nx: int,
    want_force: int,
    stamp: int,
    grid_mm: wp.array(dtype=wp.vec4, ndim=3),
    grid_f: wp.array(dtype=wp.vec3, ndim=3),
    stamps: wp.array(dtype=int, ndim=3),
):
    """Stress of the particle's F, then the scatter of mass, APIC momentum with the stress impulse and
    the external force (one pass: the stress is never stored) into ``grid_mm`` (momentum in x, y, z, mass in w:
    one address a node for both). ``part_nx``: where along the grid's first
    axis this launch's copy of the grid starts (:mod:`warpmpm.solvers.parallel`: each thread of a split step
    scatters into a copy of its own, so no two threads add to one node; 0 for a whole launch).
    ``want_force`` 1: also scatter the step's force impulse alone (stress and external, N s) into ``grid_f``
    (the rigid-mode acceleration of :mod:`warpmpm.solvers.rigid_modes` restricts it); 0: ``grid_f`` is not touched.
    ``stamp`` > 0: written into ``stamps`` at the block of the particle's first stencil node (for
    :func:`grid_update_blocks`; a block already stamped is only read); 0: ``stamps`` is not touched."""
    p = wp.tid()
    inv_dx = 1.0 / dx
    xp = x[p]
    base, fx, wx, wy, wz = stencil(xp, inv_dx)
    if stamp != 0:
        blk = wp.vec3i(base[0] // BLOCK, base[1] // BLOCK, base[2] // BLOCK)
        if stamps[blk[0], blk[1], blk[2]] != stamp:
            stamps[blk[0], blk[1], blk[2]] = stamp
    m = mass[p]
    affine = apic_stress_affine(F[p], C[p], m, vol0[p], mu[p], lam[p], dt, inv_dx)
    impulse = dt * f_ext[p]
    # what goes to node abc is w (mom + affine (abc - fx) dx) = w (u0 + a A0 + b A1 + c A2), A_k the k-th column of
    # affine dx: built up along the loops instead of a matrix-vector product a node
    Adx = affine * dx
    A0 = wp.vec3(Adx[0, 0], Adx[1, 0], Adx[2, 0])
    A1 = wp.vec3(Adx[0, 1], Adx[1, 1], Adx[2, 1])
    A2 = wp.vec3(Adx[0, 2], Adx[1, 2], Adx[2, 2])
    u0 = m * v[p] + impulse - Adx * fx
    for a in range(3):
        ua = u0 + float(a) * A0
        for b in range(3):
            uab = ua + float(b) * A1
            wab = wx[a] * wy[b]
            for c in range(3):
                w = wab * wz[c]
                q = w * (uab + float(c) * A2)
                wp.atomic_add(grid_mm, part_nx + base[0] + a, base[1] + b, base[2] + c, wp.vec4(q[0], q[1], q[2], w * m))
    if want_force != 0:  # a second pass, so the loop above stays that of a step without it (a branch in it cost 17 %)
        # w (stress (abc - fx) dx + impulse), built up along the loops as above: S_k the k-th column of stress dx
        Sdx = (affine - m * C[p]) * dx
        S0 = wp.vec3(Sdx[0, 0], Sdx[1, 0], Sdx[2, 0])
        S1 = wp.vec3(Sdx[0, 1], Sdx[1, 1], Sdx[2, 1])
        S2 = wp.vec3(Sdx[0, 2], Sdx[1, 2], Sdx[2, 2])
        scatter_linear(grid_f, part_nx, base, wx, wy, wz, impulse - Sdx * fx, S0, S1, S2)


@wp.func
def bspline_slopes(fx: wp.vec3, axis: int, inv_dx: float):
    """Derivatives (1/m) of :func:`bspline_weights` along one axis with respect to the particle's position."""
    f = fx[axis]
    return wp.vec3(-(1.5 - f) * inv_dx, -2.0 * (f - 1.0) * inv_dx, (f - 0.5) * inv_dx)


@wp.kernel
def p2g_fields(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    f_ext: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    vol0: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    field: wp.array(dtype=int),
    field_nx: int,
    dx: float,
    dt: float,
    part_nx: int,
    grid_m: wp.array(dtype=float, ndim=3),
    grid_mv: wp.array(dtype=wp.vec3, ndim=3),
    grid_g: wp.array(dtype=wp.vec3, ndim=3),
):
    """:func:`p2g` into the particle's own organ field (sliding contact), plus ``grid_g = sum m_p grad w_ip``
    (minus the field's mass gradient at the node: it points out of the organ), for the contact normals.
    ``part_nx``: the start of this launch's copy of the stacked fields (as in :func:`p2g`)."""
    p = wp.tid()
    inv_dx = 1.0 / dx
    xp = x[p]
    base, fx, wx, wy, wz = stencil(xp, inv_dx)
    gx = bspline_slopes(fx, 0, inv_dx)
    gy = bspline_slopes(fx, 1, inv_dx)
    gz = bspline_slopes(fx, 2, inv_dx)
    m = mass[p]
    affine = apic_stress_affine(F[p], C[p], m, vol0[p], mu[p], lam[p], dt, inv_dx)
    mom = m * v[p]
    impulse = dt * f_ext[p]
    off = part_nx + field[p] * field_nx
    for a in range(3):
        for b in range(3):
            for c in range(3):
                w = wx[a] * wy[b] * wz[c]
                dpos = (wp.vec3(float(a), float(b), float(c)) - fx) * dx
                ii = off + base[0] + a
                jj = base[1] + b
                kk = base[2] + c
                wp.atomic_add(grid_mv, ii, jj, kk, w * (mom + affine * dpos + impulse))
                wp.atomic_add(grid_m, ii, jj, kk, w * m)
                wp.atomic_add(grid_g, ii, jj, kk, m * wp.vec3(gx[a] * wy[b] * wz[c], wx[a] * gy[b] * wz[c], wx[a] * wy[b] * gz[c]))


@wp.func
def slip_walls(vel: wp.vec3, i: int, j: int, k: int, n: wp.vec3i, wall: int):
    """Zero the velocity component that would carry a node within ``wall`` cells of a face out of the domain."""
    out = vel
    if i < wall and out[0] < 0.0:
        out = wp.vec3(0.0, out[1], out[2])
    if i >= n[0] - wall and out[0] > 0.0:
        out = wp.vec3(0.0, out[1], out[2])
    if j < wall and out[1] < 0.0:
        out = wp.vec3(out[0], 0.0, out[2])
    if j >= n[1] - wall and out[1] > 0.0:
        out = wp.vec3(out[0], 0.0, out[2])
    if k < wall and out[2] < 0.0:
        out = wp.vec3(out[0], out[1], 0.0)
    if k >= n[2] - wall and out[2] > 0.0:
        out = wp.vec3(out[0], out[1], 0.0)
    return out


@wp.kernel
def grid_update_fields(
    grid_m: wp.array(dtype=float, ndim=3),
    grid_mv: wp.array(dtype=wp.vec3, ndim=3),
    grid_g: wp.array(dtype=wp.vec3, ndim=3),
    n_fields: int,
    field_nx: int,
    parts: int,
    i0: int,
    damping: wp.array(dtype=float),
    wall: int,
    friction: float,
    grid_v: wp.array(dtype=wp.vec4, ndim=3),
):
    """Sliding contact between organ fields (multi-velocity-field MPM, Bardenhagen et al. 2000).

    At a node where several organs have mass, the centre-of-mass velocity ``v_cm`` is what sticky contact
    would give. Organ ``f`` keeps its own velocity unless it moves toward the others along its outward
    normal ``n_f`` (from the mass gradients, ``n_f ~ g_f - sum_{o != f} g_o``): then the normal part of
    ``v_f - v_cm`` is removed (no interpenetration) and the tangential part kept (frictionless sliding) or
    reduced by at most ``friction`` times the normal correction (Coulomb). Moving apart is free (separation).
    For two organs at a node the corrections cancel in sum: momentum is conserved.

    The scattered sums come in ``parts`` copies of the stacked fields (one per thread of a split P2G,
    :mod:`warpmpm.solvers.parallel`), each ``n_fields * field_nx`` nodes long along the first axis: they are added
    here and cleared. The launch covers nodes ``i0 + tid`` along x (a split update)."""
    t, j, k = wp.tid()
    i = t + i0
    stride = n_fields * field_nx
    msum = float(0.0)
    mvsum = wp.vec3(0.0)
    gsum = wp.vec3(0.0)
    present = int(0)
    for f in range(n_fields):
        ii = f * field_nx + i
        mf = float(0.0)
        for q in range(parts):
            mf += grid_m[q * stride + ii, j, k]
        if mf > 0.0:
            msum += mf
            mvf = wp.vec3(0.0)
            gf = wp.vec3(0.0)
            for q in range(parts):
                mvf += grid_mv[q * stride + ii, j, k]
                gf += grid_g[q * stride + ii, j, k]
            mvsum += mvf
            gsum += gf
            present += 1
    n = wp.vec3i(field_nx, grid_m.shape[1], grid_m.shape[2])
    if present > 0:
        v_cm = mvsum / msum
        for f in range(n_fields):
            ii = f * field_nx + i
            mf = float(0.0)
            mvf = wp.vec3(0.0)
            gf = wp.vec3(0.0)
            for q in range(parts):
                mf += grid_m[q * stride + ii, j, k]
                mvf += grid_mv[q * stride + ii, j, k]
                gf += grid_g[q * stride + ii, j, k]
            vel = wp.vec3(0.0)
            if mf > 0.0:
                vel = mvf / mf
                if present > 1:
                    nrm = 2.0 * gf - gsum
                    ln = wp.length(nrm)
                    if ln > 0.0:
                        nrm = nrm / ln
                        rel = vel - v_cm
                        vn = wp.dot(rel, nrm)
                        if vn > 0.0:  # approaching the others: remove the normal part
                            tang = rel - vn * nrm
                            lt = wp.length(tang)
                            if friction > 0.0 and lt > 0.0:
                                tang = tang * wp.max(0.0, 1.0 - friction * vn / lt)
                            vel = v_cm + tang
                vel = slip_walls(vel * damping[0], i, j, k, n, wall)
                for q in range(parts):
                    grid_m[q * stride + ii, j, k] = 0.0
                    grid_mv[q * stride + ii, j, k] = wp.vec3(0.0)
                    grid_g[q * stride + ii, j, k] = wp.vec3(0.0)
            grid_v[ii, j, k] = wp.vec4(vel[0], vel[1], vel[2], 0.0)
    else:
        for f in range(n_fields):
            grid_v[f * field_nx + i, j, k] = wp.vec4(0.0)


@wp.func
def update_node(grid_mm: wp.array(dtype=wp.vec4, ndim=3), parts: int, i: int, j: int, k: int, damping: float, wall: int,
                want_force: int, grid_f: wp.array(dtype=wp.vec3, ndim=3), grid_v: wp.array(dtype=wp.vec4, ndim=3),
                force_sum: wp.array(dtype=wp.vec3, ndim=3)):
    """The grid update of node ``(i, j, k)``: its ``parts`` copies of mass and momentum added and cleared (only where
    there is mass: the others were never written), velocity = momentum / mass, damped, slip walls; ``grid_v`` and,
    with ``want_force``, ``force_sum`` written (zero where there is no mass)."""
    nx = grid_v.shape[0]
    mm = wp.vec4(0.0)
    for q in range(parts):
        mm += grid_mm[q * nx + i, j, k]
    m = mm[3]
    vel = wp.vec3(0.0)
    fsum = wp.vec3(0.0)
    if m > 0.0:
        for q in range(parts):
            grid_mm[q * nx + i, j, k] = wp.vec4(0.0)
            if want_force != 0:
                fsum += grid_f[q * nx + i, j, k]
                grid_f[q * nx + i, j, k] = wp.vec3(0.0)
        mv = wp.vec3(mm[0], mm[1], mm[2])
        vel = slip_walls(mv / m * damping, i, j, k, wp.vec3i(nx, grid_v.shape[1], grid_v.shape[2]), wall)
    grid_v[i, j, k] = wp.vec4(vel[0], vel[1], vel[2], 0.0)
    if want_force != 0:
        force_sum[i, j, k] = fsum


@wp.kernel
def grid_update(
    grid_mm: wp.array(dtype=wp.vec4, ndim=3),
    parts: int,
    i0: int,
    damping: wp.array(dtype=float),
    wall: int,
    want_force: int,
    grid_f: wp.array(dtype=wp.vec3, ndim=3),
    grid_v: wp.array(dtype=wp.vec4, ndim=3),
    force_sum: wp.array(dtype=wp.vec3, ndim=3),
):
    """Momentum -> velocity, velocity damping ``v <- v * damping[0]``, slip walls ``wall`` cells thick, at every node
    (:func:`update_node`; :func:`grid_update_blocks` visits only the blocks that hold mass). The
    velocity goes into x, y, z of ``grid_v`` (w unused: a 16-byte node that G2P reads with one aligned load;
    measured: G2P 26.5 -> 20.5 ms on the paper-resolution phantom, one thread, against a vec3 grid).

    The scattered mass and momentum come in ``parts`` copies of the grid stacked along x (one per thread of
    a split P2G, :mod:`warpmpm.solvers.parallel`; 1 for a whole one): they are added here. Clears what it has read,
    so the next step's ``p2g`` scatters into a clean grid without a separate clearing pass over every node
    (the grid starts zeroed). The launch covers nodes ``i0 + tid`` along x (a split update).
    ``want_force`` 1: the copies of the force impulse ``grid_f`` are added into ``force_sum`` (every node written)
    and cleared the same way."""
    t, j, k = wp.tid()
    update_node(grid_mm, parts, t + i0, j, k, damping[0], wall, want_force, grid_f, grid_v, force_sum)


@wp.kernel
def grid_update_blocks(
    grid_mm: wp.array(dtype=wp.vec4, ndim=3),
    parts: int,
    b0: int,
    stamps: wp.array(dtype=int, ndim=3),
    stamp: int,
    updated: wp.array(dtype=int, ndim=3),
    damping: wp.array(dtype=float),
    wall: int,
    want_force: int,
    grid_f: wp.array(dtype=wp.vec3, ndim=3),
    grid_v: wp.array(dtype=wp.vec4, ndim=3),
    force_sum: wp.array(dtype=wp.vec3, ndim=3),
):
    """:func:`grid_update` over the blocks of :data:`BLOCK`^3 nodes that hold mass, one thread a block (blocks
    ``b0 + tid`` along x: a split update). P2G writes ``stamp`` (this step's number) into ``stamps`` at the block of
    each particle's first stencil node; a stencil reaches one block further along each axis, so a block holds mass
    when it or one of its 7 lower neighbours carries this step's stamp. ``updated``: 1 where the block was updated
    with mass last step. A block with mass, or with ``updated`` set, is updated node by node as :func:`grid_update`
    would (the second writes the zero velocities and force sums of a block that has just emptied); every other
    block already holds the zeros a dense update would write, so the result is the dense update's, node for node.
    On the default phantom one node in nine lies in the particles' stencils."""
    t, bj, bk = wp.tid()
    bi = t + b0
    active = int(0)
    for di in range(2):
        for dj in range(2):
            for dk in range(2):
                if bi >= di and bj >= dj and bk >= dk:
                    if stamps[bi - di, bj - dj, bk - dk] == stamp:
                        active = 1
    if active == 0 and updated[bi, bj, bk] == 0:
        return
    updated[bi, bj, bk] = active
    d = damping[0]
    nx = grid_v.shape[0]
    ny = grid_v.shape[1]
    nz = grid_v.shape[2]
    for di in range(BLOCK):
        i = bi * BLOCK + di
        if i < nx:
            for dj in range(BLOCK):
                j = bj * BLOCK + dj
                if j < ny:
                    for dk in range(BLOCK):
                        k = bk * BLOCK + dk
                        if k < nz:
                            update_node(grid_mm, parts, i, j, k, d, wall, want_force, grid_f, grid_v, force_sum)


@wp.func
def is_finite_vec(a: wp.vec3):
    return wp.isfinite(a[0]) and wp.isfinite(a[1]) and wp.isfinite(a[2])


@wp.func
def gather_velocity(grid_v: wp.array(dtype=Any, ndim=3), base: wp.vec3i, fx: wp.vec3, wx: wp.vec3, wy: wp.vec3, wz: wp.vec3,
                    inv_dx: float):
    """A particle's velocity ``v = sum_i w_i v_i`` and APIC matrix ``C = 4/dx^2 sum_i w_i v_i (x_i - x_p)^T`` from its
    3x3x3 stencil, the weights factorised by axis: with ``x_i - x_p = (abc - fx) dx``, ``C = 4/dx (T - v fx^T)`` where
    column ``k`` of ``T`` sums ``w_i v_i`` times the node's k-th stencil index, and every sum runs innermost over z,
    then y, then x (6 multiply-adds a node instead of ~30; measured: the gather 13.4 -> 8.9 ms on 113k particles, one
    thread; the same v and C to float32 rounding, 3e-7 and 6e-7 relative). ``grid_v``: any node type whose first three
    components are the vector (G2P's vec4 velocities; the quasi-static solver's vec3 displacements, whose ``C`` is their
    MLS gradient)."""
    v = wp.vec3(0.0)
    t0 = wp.vec3(0.0)
    t1 = wp.vec3(0.0)
    t2 = wp.vec3(0.0)
    for a in range(3):
        sa = wp.vec3(0.0)
        sb = wp.vec3(0.0)
        sc = wp.vec3(0.0)
        for b in range(3):
            r = wp.vec3(0.0)
            rc = wp.vec3(0.0)
            for c in range(3):
                g4 = grid_v[base[0] + a, base[1] + b, base[2] + c]
                gw = wz[c] * wp.vec3(g4[0], g4[1], g4[2])
                r += gw
                rc += float(c) * gw
            sa += wy[b] * r
            sb += (wy[b] * float(b)) * r
            sc += wy[b] * rc
        v += wx[a] * sa
        t0 += (wx[a] * float(a)) * sa
        t1 += wx[a] * sb
        t2 += wx[a] * sc
    C = wp.mat33(t0[0] - v[0] * fx[0], t1[0] - v[0] * fx[1], t2[0] - v[0] * fx[2],
                 t0[1] - v[1] * fx[0], t1[1] - v[1] * fx[1], t2[1] - v[1] * fx[2],
                 t0[2] - v[2] * fx[0], t1[2] - v[2] * fx[1], t2[2] - v[2] * fx[2])
    return v, (4.0 * inv_dx) * C


@wp.kernel
def g2p(
    grid_v: wp.array(dtype=wp.vec4, ndim=3),
    field: wp.array(dtype=int),
    field_nx: int,
    x_in: wp.array(dtype=wp.vec3),
    carry_in: wp.array(dtype=wp.vec3),
    F_in: wp.array(dtype=wp.mat33),
    dx: float,
    dt: float,
    x_min: float,
    x_max: wp.vec3,
    step: int,
    index0: int,
    x_out: wp.array(dtype=wp.vec3),
    carry_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
    status: wp.array(dtype=int),
):
    """Gather velocity and C, advect, update F. ``status`` = [code, first bad particle, first bad step];
    ``index0`` is the global index of the launch's first particle (a launch over part of the particles).

    With ``field_nx`` > 0 (sliding contact) each organ has its own grid velocity field, stacked along the
    first axis: the particle reads field ``field[p]``, nodes ``field[p] * field_nx + i``."""
    p = wp.tid()
    inv_dx = 1.0 / dx
    xp = x_in[p]
    base, fx, wx, wy, wz = stencil(xp, inv_dx)
    if field_nx > 0:
        base = wp.vec3i(base[0] + field[p] * field_nx, base[1], base[2])
    new_v, new_C = gather_velocity(grid_v, base, fx, wx, wy, wz, inv_dx)
    # Compensated (Kahan) position update: near equilibrium a step moves a particle by less than float32
    # resolves at its position (~7e-9 m at 6 cm from the grid origin) while F integrates the same velocity
    # gradient; positions that cannot follow F let stress build with no motion to balance it (measured:
    # a relaxed free block's |F - I| grew 0.0008 -> 0.0018 over 12,000 steps with every particle still).
    # ``carry`` keeps the part of the move the rounded position lost, exactly (Sterbenz), for the next step.
    move = dt * new_v + carry_in[p]
    new_x = xp + move
    carry = move - (new_x - xp)
    F_new = (wp.identity(n=3, dtype=float) + dt * new_C) * F_in[p]
    code = int(0)
    if not (is_finite_vec(new_x) and is_finite_vec(new_v) and wp.isfinite(wp.determinant(F_new))):
        code = STATUS_NONFINITE
        new_x = xp
        carry = wp.vec3(0.0)
        new_v = wp.vec3(0.0)
        new_C = wp.mat33(0.0)
        F_new = F_in[p]
    # Keep the particle where its 3x3x3 stencil stays inside the grid; flag it when clamped.
    clamped = wp.vec3(wp.clamp(new_x[0], x_min, x_max[0]), wp.clamp(new_x[1], x_min, x_max[1]), wp.clamp(new_x[2], x_min, x_max[2]))
    if code == 0 and (clamped[0] != new_x[0] or clamped[1] != new_x[1] or clamped[2] != new_x[2]):
        code = STATUS_LEFT_GRID
        carry = wp.vec3(0.0)
    if code != 0:
        wp.atomic_max(status, 0, code)
        wp.atomic_min(status, 1, index0 + p)
        wp.atomic_min(status, 2, step)
    x_out[p] = clamped
    carry_out[p] = carry
    v_out[p] = new_v
    C_out[p] = new_C
    F_out[p] = F_new


@wp.kernel
def stiffness_rayleigh(
    v_in: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    accel_prev: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    weight: wp.array(dtype=float),
    damping: wp.array(dtype=float),
    dt: float,
    sums: wp.array(dtype=float, ndim=2),
):
    """Rayleigh quotient of the stiffness the motion sees (adaptive dynamic relaxation, Underwood 1983).

    The undamped acceleration of this step is ``a_n = (v_out / damping - v_in) / dt``; between two steps it
    changes by ``a_n - a_(n-1) = -(K / M) dx`` with ``dx = v_in dt`` the move in between, so
    ``omega^2 = -sum w m (a_n - a_(n-1)) . v_in / (dt sum w m |v_in|^2)`` is the squared frequency of the
    mode the body is moving in. Accumulates the numerator (without 1/dt) and the denominator into ``sums``
    (particles of ``weight`` 0, the driven ones, left out: their drive is a spring of its own), spread over
    ``sums.shape[1]`` slots by particle index so that a GPU's atomics do not all queue on one address."""
    p = wp.tid()
    vi = v_in[p]
    a = (v_out[p] / damping[0] - vi) / dt
    da = a - accel_prev[p]
    accel_prev[p] = a
    w = mass[p] * weight[p]
    if w > 0.0:
        slot = p % sums.shape[1]
        wp.atomic_add(sums, 0, slot, -w * wp.dot(da, vi))
        wp.atomic_add(sums, 1, slot, w * wp.dot(vi, vi))


@wp.kernel
def adapt_damping(
    sums: wp.array(dtype=float, ndim=2),
    memory: wp.array(dtype=float),
    keep: float,
    dt: float,
    gamma_min: float,
    gamma_max: float,
    damping: wp.array(dtype=float),
):
    """One thread: critical damping ``gamma = 2 omega`` of the mode the body moves in, from the Rayleigh
    sums of :func:`stiffness_rayleigh` averaged over the last ~``1 / (1 - keep)`` steps, clamped to
    ``[gamma_min, gamma_max]`` (1/s); writes the velocity factor ``exp(-gamma dt)`` and clears the sums.
    With nothing moving (no denominator) the factor stays as it was."""
    num = keep * memory[0]
    den = keep * memory[1]
    for slot in range(sums.shape[1]):
        num += sums[0, slot]
        den += sums[1, slot]
        sums[0, slot] = 0.0
        sums[1, slot] = 0.0
    memory[0] = num
    memory[1] = den
    if den > 0.0:
        omega2 = wp.max(num / (den * dt), 0.0)
        gamma = wp.clamp(2.0 * wp.sqrt(omega2), gamma_min, gamma_max)
        damping[0] = wp.exp(-gamma * dt)
