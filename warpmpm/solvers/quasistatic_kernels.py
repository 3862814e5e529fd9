"""Kernels of the quasi-static solver (:mod:`warpmpm.solvers.quasistatic`): the matrix-free stiffness product, the
Newton iteration's forces, the conjugate gradient's steps and its coarse level, the particle move."""

import warp as wp

from . import explicit_kernels as kernels

__all__ = ["node_index", "internal_and_drive_forces", "add_copies", "apply_stiffness", "finish_matvec",
           "inverse_diagonal", "RZ", "PAP", "RZ_NEXT", "RR", "RR_LAST", "RZ_LAST", "DOT_SLOTS", "add_partial",
           "cg_reduce", "cg_start", "cg_dot", "coarse_solve", "cg_advance", "cg_direction", "cg_next", "move_particles", "update_multipliers"]

# forward kernels only, no adjoints to compile (why: warpmpm.solvers.explicit_kernels)
wp.set_module_options({"enable_backward": False})


@wp.func
def node_index(i: int, j: int, k: int, ny: int, nz: int):
    """Index of grid node (i, j, k) in the flat node arrays."""
    return (i * ny + j) * nz + k


@wp.kernel
def internal_and_drive_forces(
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    vol0: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    pen_k: wp.array(dtype=float),
    pen_P: wp.array(dtype=wp.mat33),
    target: wp.array(dtype=wp.vec3),
    multiplier: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    dx: float,
    ny: int,
    nz: int,
    n0: int,
    force: wp.array(dtype=wp.vec3),
    diag: wp.array(dtype=wp.vec3),
    node_mass: wp.array(dtype=float),
):
    """Nodal force (N): the internal force of the fixed-corotated stress of ``F`` and the driven particles' penalty
    and multiplier forces; the diagonal of the small-strain stiffness plus the penalty (Jacobi preconditioner); and
    the nodal mass (kg, of the solver's scaled densities) for the regularisation. ``n0``: the first node of this
    launch's copy of the three node arrays (a launch over part of the particles on a thread of its own, added by
    :func:`add_copies`; 0 for a whole launch)."""
    p = wp.tid()
    inv_dx = 1.0 / dx
    xp = x[p]
    base, fx, wx, wy, wz = kernels.stencil(xp, inv_dx)
    c = 4.0 * inv_dx * inv_dx
    V = vol0[p]
    m_u = mu[p]
    l = lam[p]
    s = (c * V) * kernels.fixed_corotated_kirchhoff(F[p], m_u, l)
    P = pen_P[p]
    k = pen_k[p]
    fd = k * (P * (target[p] - xp)) + P * multiplier[p]
    for a in range(3):
        for b in range(3):
            for cc in range(3):
                w = wx[a] * wy[b] * wz[cc]
                r = (wp.vec3(float(a), float(b), float(cc)) - fx) * dx
                n = n0 + node_index(base[0] + a, base[1] + b, base[2] + cc, ny, nz)
                wp.atomic_add(force, n, w * (fd - s * r))
                cw2 = V * (c * w) * (c * w)
                r2 = wp.dot(r, r)
                d = wp.vec3(m_u * r2 + (m_u + l) * r[0] * r[0], m_u * r2 + (m_u + l) * r[1] * r[1], m_u * r2 + (m_u + l) * r[2] * r[2])
                wp.atomic_add(diag, n, cw2 * d + (k * w * w) * wp.vec3(P[0, 0], P[1, 1], P[2, 2]))
                wp.atomic_add(node_mass, n, w * mass[p])



@wp.kernel
def add_copies(force: wp.array(dtype=wp.vec3), diag: wp.array(dtype=wp.vec3), node_mass: wp.array(dtype=float), parts: int):
    """Add the ``parts`` copies of :func:`internal_and_drive_forces`' node arrays (one after the other, one per
    thread) into the first, and clear the others (so only the first needs clearing before the next scatter)."""
    i = wp.tid()
    nn = force.shape[0] // parts
    f = force[i]
    dg = diag[i]
    mi = node_mass[i]
    for q in range(1, parts):
        j = q * nn + i
        f += force[j]
        dg += diag[j]
        mi += node_mass[j]
        force[j] = wp.vec3(0.0)
        diag[j] = wp.vec3(0.0)
        node_mass[j] = 0.0
    force[i] = f
    diag[i] = dg
    node_mass[i] = mi


@wp.kernel
def apply_stiffness(
    x: wp.array(dtype=wp.vec3),
    vol0: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    pen_k: wp.array(dtype=float),
    pen_P: wp.array(dtype=wp.mat33),
    dx: float,
    ny: int,
    nz: int,
    v: wp.array(dtype=wp.vec3, ndim=3),
    i0: int,
    out: wp.array(dtype=wp.vec3, ndim=3),
):
    """``out += (K + penalty) v`` for one particle's share: gather ``G_p v`` and the particle's displacement,
    then scatter ``G_p^T V0 (mu (G + G^T) + lambda tr(G) I)`` and the penalty ``k P (sum w v)``. ``v``, ``out``: nodal
    vectors as (nx, ny, nz) views of flat node arrays (:func:`grid_view`); the weights factorised by axis in both
    (:func:`warpmpm.solvers.explicit_kernels.gather_velocity`, :func:`warpmpm.solvers.explicit_kernels.scatter_linear`). ``i0``: where along x this
    launch's copy of ``out`` starts (a launch over part of the particles on a thread of its own scatters into a copy of
    its own, :mod:`warpmpm.solvers.parallel`; 0 for a whole launch); :func:`finish_matvec` adds the copies."""
    p = wp.tid()
    inv_dx = 1.0 / dx
    base, fx, wx, wy, wz = kernels.stencil(x[p], inv_dx)
    vp, G = kernels.gather_velocity(v, base, fx, wx, wy, wz, inv_dx)
    c = 4.0 * inv_dx * inv_dx
    dtau = mu[p] * (G + wp.transpose(G)) + (lam[p] * (G[0, 0] + G[1, 1] + G[2, 2])) * wp.identity(n=3, dtype=float)
    s = (c * vol0[p]) * dtau
    fd = pen_k[p] * (pen_P[p] * vp)
    S = s * dx
    kernels.scatter_linear(out, i0, base, wx, wy, wz, fd - S * fx, wp.vec3(S[0, 0], S[1, 0], S[2, 0]), wp.vec3(S[0, 1], S[1, 1], S[2, 1]),
                           wp.vec3(S[0, 2], S[1, 2], S[2, 2]))


@wp.kernel
def finish_matvec(
    nodes: wp.array(dtype=int),
    Av: wp.array(dtype=wp.vec3),
    parts: int,
    v: wp.array(dtype=wp.vec3),
    node_mass: wp.array(dtype=float),
    k_reg: float,
    partial: wp.array(dtype=wp.float64, ndim=2),
):
    """``Av <- A v`` with ``A = K + k_reg M`` on the nodes particles touch (``nodes``: the conjugate gradient runs on
    them alone; an untouched node has no force and keeps a zero displacement); ``v . A v`` into ``partial[PAP]``.
    ``Av`` holds ``parts`` copies of the node array one after the other (one per thread of a split
    :func:`apply_stiffness`): they are added into the first and cleared (so only the first needs clearing before the
    next product)."""
    i = nodes[wp.tid()]
    mi = node_mass[i]
    vi = v[i]
    nn = node_mass.shape[0]
    a = Av[i]
    for q in range(1, parts):
        a += Av[q * nn + i]
        Av[q * nn + i] = wp.vec3(0.0)
    if mi > 0.0:
        a += (k_reg * mi) * vi
    else:
        a = vi
    Av[i] = a
    add_partial(partial, PAP, i, wp.float64(wp.dot(vi, a)))


@wp.kernel
def inverse_diagonal(nodes: wp.array(dtype=int), diag: wp.array(dtype=wp.vec3), node_mass: wp.array(dtype=float), k_reg: float,
                     inv: wp.array(dtype=wp.vec3)):
    """Jacobi preconditioner: ``1 / (D + k_reg m)`` at the ``nodes`` particles touch (1 at any other listed)."""
    i = nodes[wp.tid()]
    mi = node_mass[i]
    d = diag[i] + wp.vec3(k_reg * mi)
    if mi > 0.0:
        inv[i] = wp.vec3(1.0 / d[0], 1.0 / d[1], 1.0 / d[2])
    else:
        inv[i] = wp.vec3(1.0)


#: slots of the conjugate-gradient scalars array: r.z, p.A p, the next r.z, r.r, the last iteration's r.r
RZ = wp.constant(0)
PAP = wp.constant(1)
RZ_NEXT = wp.constant(2)
RR = wp.constant(3)
RR_LAST = wp.constant(4)
RZ_LAST = wp.constant(5)

#: slots each dot product of the conjugate gradient is spread over (by node index), then summed by one thread: a GPU
#: would serialise ~130,000 atomics on one address an iteration otherwise (an estimate: docs/performance.md)
DOT_SLOTS = 64


@wp.func
def add_partial(partial: wp.array(dtype=wp.float64, ndim=2), row: int, i: int, value: wp.float64):
    """Add a node's share of the sum ``row`` into slot ``i % DOT_SLOTS``."""
    wp.atomic_add(partial, row, i % partial.shape[1], value)


@wp.kernel
def cg_reduce(partial: wp.array(dtype=wp.float64, ndim=2), scalars: wp.array(dtype=wp.float64)):
    """One thread: add every row of ``partial`` into ``scalars`` and clear it."""
    for row in range(partial.shape[0]):
        acc = wp.float64(0.0)
        for k in range(partial.shape[1]):
            acc += partial[row, k]
            partial[row, k] = wp.float64(0.0)
        scalars[row] = scalars[row] + acc


@wp.kernel
def cg_start(nodes: wp.array(dtype=int), b: wp.array(dtype=wp.vec3), inv_diag: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3), r: wp.array(dtype=wp.vec3),
             z: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3), partial: wp.array(dtype=wp.float64, ndim=2)):
    """``x = 0``, ``r = b``, ``z = D^-1 r``, ``p = z``; r.z and r.r into ``partial[RZ]``, ``partial[RR]`` (with a coarse
    correction, :func:`cg_dot` recomputes r.z and sets p once it is added). Here and in the other node kernels of the
    conjugate gradient, thread ``t`` works on node ``nodes[t]``: the nodes particles touch, ascending (elsewhere every
    vector of the recurrence is zero, so the sums are those over every node, to the bit)."""
    i = nodes[wp.tid()]
    ri = b[i]
    zi = wp.cw_mul(inv_diag[i], ri)
    x[i] = wp.vec3(0.0)
    r[i] = ri
    z[i] = zi
    p[i] = zi
    add_partial(partial, RZ, i, wp.float64(wp.dot(ri, zi)))
    add_partial(partial, RR, i, wp.float64(wp.dot(ri, ri)))


@wp.kernel
def cg_dot(nodes: wp.array(dtype=int), r: wp.array(dtype=wp.vec3), z: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3), slot: int, set_p: int,
           partial: wp.array(dtype=wp.float64, ndim=2)):
    """r.z over the nodes into ``partial[slot]`` (after a coarse correction changed z); ``p = z`` with ``set_p``."""
    i = nodes[wp.tid()]
    zi = z[i]
    add_partial(partial, slot, i, wp.float64(wp.dot(r[i], zi)))
    if set_p != 0:
        p[i] = zi


@wp.kernel
def coarse_solve(E_inv: wp.array(dtype=wp.float64, ndim=2), t: wp.array(dtype=wp.float64), y: wp.array(dtype=wp.float64)):
    """``y = E^-1 t`` (one thread a coarse unknown), then the next restriction may start afresh in ``t``."""
    j = wp.tid()
    acc = wp.float64(0.0)
    for l in range(E_inv.shape[1]):
        acc += E_inv[j, l] * t[l]
    y[j] = acc


@wp.kernel
def cg_advance(nodes: wp.array(dtype=int), inv_diag: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3), Ap: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3),
               r: wp.array(dtype=wp.vec3), z: wp.array(dtype=wp.vec3), rz_here: int, scalars: wp.array(dtype=wp.float64),
               partial: wp.array(dtype=wp.float64, ndim=2)):
    """``alpha = r.z / p.Ap``; ``x += alpha p``, ``r -= alpha A p``, ``z = M r``; the new r.z and r.r into ``partial``."""
    i = nodes[wp.tid()]
    pap = scalars[PAP]
    alpha = float(0.0)
    if pap > wp.float64(0.0):
        alpha = float(scalars[RZ] / pap)
    x[i] = x[i] + alpha * p[i]
    ri = r[i] - alpha * Ap[i]
    zi = wp.cw_mul(inv_diag[i], ri)
    r[i] = ri
    z[i] = zi
    if rz_here != 0:
        add_partial(partial, RZ_NEXT, i, wp.float64(wp.dot(ri, zi)))
    add_partial(partial, RR, i, wp.float64(wp.dot(ri, ri)))


@wp.kernel
def cg_direction(nodes: wp.array(dtype=int), z: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3), scalars: wp.array(dtype=wp.float64)):
    """``p = z + beta p`` with ``beta = r.z (new) / r.z (old)``."""
    i = nodes[wp.tid()]
    rz = scalars[RZ]
    beta = float(0.0)
    if rz > wp.float64(0.0):
        beta = float(scalars[RZ_NEXT] / rz)
    p[i] = z[i] + beta * p[i]


@wp.kernel
def cg_next(scalars: wp.array(dtype=wp.float64)):
    """One thread: the new r.z becomes the current one, r.r is kept as the last one; the sums restart."""
    scalars[RR_LAST] = scalars[RR]
    scalars[RZ_LAST] = scalars[RZ_NEXT]
    scalars[RZ] = scalars[RZ_NEXT]
    scalars[RZ_NEXT] = wp.float64(0.0)
    scalars[PAP] = wp.float64(0.0)
    scalars[RR] = wp.float64(0.0)


@wp.kernel
def move_particles(
    du: wp.array(dtype=wp.vec3, ndim=3),
    scale: float,
    apply: int,
    dx: float,
    ny: int,
    nz: int,
    x_min: float,
    x_max: wp.vec3,
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    move: wp.array(dtype=float),
    strain: wp.array(dtype=float),
    index0: int,
    status: wp.array(dtype=int),
):
    """Move every particle by the interpolated grid displacement ``scale du`` and update ``F <- (I + G du) F``;
    ``move`` gets each particle's move (m). With ``apply`` 0 only ``move`` is written (to size the step). A
    non-finite result or a particle leaving the grid is flagged in ``status`` ([code, first particle]) and not applied."""
    p = wp.tid()
    xp = x[p]
    inv_dx = 1.0 / dx
    base, fx, wx, wy, wz = kernels.stencil(xp, inv_dx)
    u1, G1 = kernels.gather_velocity(du, base, fx, wx, wy, wz, inv_dx)
    G = scale * G1
    up = scale * u1
    new_x = xp + up
    F_new = (wp.identity(n=3, dtype=float) + G) * F[p]
    if apply == 0:
        move[p] = wp.length(up)
        strain[p] = wp.sqrt(wp.ddot(G, G))
        return
    code = int(0)
    if not (kernels.is_finite_vec(new_x) and wp.isfinite(wp.determinant(F_new))):
        code = kernels.STATUS_NONFINITE
    elif (new_x[0] < x_min or new_x[1] < x_min or new_x[2] < x_min or new_x[0] > x_max[0] or new_x[1] > x_max[1]
          or new_x[2] > x_max[2]):
        code = kernels.STATUS_LEFT_GRID
    if code != 0:
        wp.atomic_max(status, 0, code)
        wp.atomic_min(status, 1, index0 + p)
        move[p] = 0.0
    else:
        x[p] = new_x
        F[p] = F_new
        move[p] = wp.length(up)


@wp.kernel
def update_multipliers(
    driven: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    pen_k: wp.array(dtype=float),
    pen_P: wp.array(dtype=wp.mat33),
    target: wp.array(dtype=wp.vec3),
    multiplier: wp.array(dtype=wp.vec3),
    exact: int,
    err2: wp.array(dtype=float),
):
    """Augmented Lagrangian: each driven particle's multiplier takes up its penalty force ``k P (t - x)``, so the
    next iterations pull it the rest of the way; ``err2`` sums the squared driven residual (m^2)."""
    j = wp.tid()
    p = driven[j]
    e = pen_P[p] * (target[p] - x[p])
    if exact != 0:
        multiplier[p] = multiplier[p] + pen_k[p] * e
    wp.atomic_add(err2, 0, wp.dot(e, e))
