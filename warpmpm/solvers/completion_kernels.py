"""Warp kernels of the completion solve (:mod:`warpmpm.solvers.completion`): the small-strain stiffness of material
points on a quadratic B-spline grid (the MPM's basis), the springs that tie points to observed positions, and the
interpolation of node displacements to points.

Units: positions in grid cells relative to the grid origin (``x / dx``), node displacements in mm, moduli in Pa,
point volumes in mm^3; a stiffness entry is then in Pa mm (N/m: the units cancel consistently, the solve only needs
them consistent). The stiffness is accumulated in a *stencil* array ``(node, 125 neighbour offsets, 9)``: the 3 x 3
block coupling a node to its neighbour at offset ``(di, dj, dk)`` in ``-2..2``, row-major, which the host turns into a
sparse matrix.
"""

import warp as wp

__all__ = ["spline_w", "spline_dw", "node_weight_grad", "node_of", "offset_slot", "assemble_stiffness",
           "assemble_springs", "spring_load", "interpolate"]

wp.set_module_options({"enable_backward": False})


@wp.func
def spline_w(f: float, a: int):
    """Quadratic B-spline weight of the node ``a`` (0, 1, 2) of a point at fractional offset ``f`` from its base node."""
    if a == 0:
        return 0.5 * (1.5 - f) * (1.5 - f)
    if a == 1:
        return 0.75 - (f - 1.0) * (f - 1.0)
    return 0.5 * (f - 0.5) * (f - 0.5)


@wp.func
def spline_dw(f: float, a: int):
    """d/dx (in cells) of :func:`spline_w`."""
    if a == 0:
        return f - 1.5
    if a == 1:
        return -2.0 * (f - 1.0)
    return f - 0.5


@wp.func
def node_weight_grad(x: wp.vec3, a: int, inv_dx: float):
    """The weight (w) and gradient (1/mm) of the ``a``-th (0..26) node of the point at ``x`` (cells), as a vec4."""
    bx = wp.floor(x[0] - 0.5)
    by = wp.floor(x[1] - 0.5)
    bz = wp.floor(x[2] - 0.5)
    fx = x[0] - bx
    fy = x[1] - by
    fz = x[2] - bz
    ai = a / 9
    aj = (a / 3) % 3
    ak = a % 3
    wx = spline_w(fx, ai)
    wy = spline_w(fy, aj)
    wz = spline_w(fz, ak)
    return wp.vec4(wx * wy * wz, spline_dw(fx, ai) * wy * wz * inv_dx, wx * spline_dw(fy, aj) * wz * inv_dx,
                   wx * wy * spline_dw(fz, ak) * inv_dx)


@wp.func
def node_of(x: wp.vec3, a: int, ny: int, nz: int):
    """Flat index ``(i ny + j) nz + k`` of the ``a``-th node of the point at ``x`` (cells)."""
    i = int(wp.floor(x[0] - 0.5)) + a / 9
    j = int(wp.floor(x[1] - 0.5)) + (a / 3) % 3
    k = int(wp.floor(x[2] - 0.5)) + a % 3
    return (i * ny + j) * nz + k


@wp.func
def offset_slot(a: int, b: int):
    """Slot (0..124) of the offset from node ``a`` to node ``b`` of one point's 27."""
    di = b / 9 - a / 9 + 2
    dj = (b / 3) % 3 - (a / 3) % 3 + 2
    dk = b % 3 - a % 3 + 2
    return (di * 5 + dj) * 5 + dk


@wp.kernel
def assemble_stiffness(x: wp.array(dtype=wp.vec3), vol: wp.array(dtype=float), lam: wp.array(dtype=float),
                       mu: wp.array(dtype=float), inv_dx: float, ny: int, nz: int, active: wp.array(dtype=int),
                       stencil: wp.array(dtype=wp.float64, ndim=3)):
    """``K_ab[i, j] += V (lam g_a,i g_b,j + mu g_a,j g_b,i + mu (g_a . g_b) delta_ij)`` for every pair of a point's
    nodes: the Hessian of ``V (lam/2 tr(eps)^2 + mu eps:eps)`` with ``eps`` the small strain of the node motion."""
    p = wp.tid()
    xp = x[p]
    v = vol[p]
    la = lam[p] * v
    m = mu[p] * v
    for a in range(27):
        ga4 = node_weight_grad(xp, a, inv_dx)
        ga = wp.vec3(ga4[1], ga4[2], ga4[3])
        row = active[node_of(xp, a, ny, nz)]
        for b in range(27):
            gb4 = node_weight_grad(xp, b, inv_dx)
            gb = wp.vec3(gb4[1], gb4[2], gb4[3])
            s = offset_slot(a, b)
            d = m * wp.dot(ga, gb)
            for i in range(3):
                for j in range(3):
                    val = la * ga[i] * gb[j] + m * ga[j] * gb[i]
                    if i == j:
                        val = val + d
                    wp.atomic_add(stencil, row, s, i * 3 + j, wp.float64(val))


@wp.kernel
def assemble_springs(x: wp.array(dtype=wp.vec3), k: wp.array(dtype=float), P: wp.array(dtype=wp.mat33), ny: int, nz: int,
                     active: wp.array(dtype=int), stencil: wp.array(dtype=wp.float64, ndim=3)):
    """``K_ab += k w_a w_b P``: a spring of stiffness ``k`` pulling the point's interpolated motion, along the
    directions of the projector ``P``, toward a target (its right-hand side is :func:`spring_load`)."""
    p = wp.tid()
    xp = x[p]
    kp = k[p]
    Pp = P[p]
    for a in range(27):
        wa = node_weight_grad(xp, a, 1.0)[0]
        row = active[node_of(xp, a, ny, nz)]
        for b in range(27):
            wb = node_weight_grad(xp, b, 1.0)[0]
            s = offset_slot(a, b)
            c = kp * wa * wb
            for i in range(3):
                for j in range(3):
                    wp.atomic_add(stencil, row, s, i * 3 + j, wp.float64(c * Pp[i, j]))


@wp.kernel
def spring_load(x: wp.array(dtype=wp.vec3), k: wp.array(dtype=float), P: wp.array(dtype=wp.mat33), d: wp.array(dtype=wp.vec3),
                ny: int, nz: int, active: wp.array(dtype=int), f: wp.array(dtype=wp.vec3d)):
    """``f_a += k w_a P d``: the load of the springs toward displacements ``d`` (mm)."""
    p = wp.tid()
    xp = x[p]
    q = k[p] * (P[p] @ d[p])
    for a in range(27):
        wa = node_weight_grad(xp, a, 1.0)[0]
        wp.atomic_add(f, active[node_of(xp, a, ny, nz)], wp.vec3d(wp.float64(wa * q[0]), wp.float64(wa * q[1]), wp.float64(wa * q[2])))


@wp.kernel
def interpolate(x: wp.array(dtype=wp.vec3), u: wp.array(dtype=wp.vec3d), ny: int, nz: int, active: wp.array(dtype=int),
                out: wp.array(dtype=wp.vec3)):
    """``u_p = sum_a w_a u_a``: the displacement (mm) of the point at ``x`` (cells)."""
    p = wp.tid()
    xp = x[p]
    s = wp.vec3(0.0)
    for a in range(27):
        wa = node_weight_grad(xp, a, 1.0)[0]
        ua = u[active[node_of(xp, a, ny, nz)]]
        s = s + wa * wp.vec3(float(ua[0]), float(ua[1]), float(ua[2]))
    out[p] = s
