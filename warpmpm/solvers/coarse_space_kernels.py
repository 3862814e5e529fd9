"""Kernels of the coarse space (:mod:`warpmpm.solvers.coarse_space`): a particle's B-spline stencil for the host, a
group's modes at a node, and the restriction ``Z^T r`` and prolongation ``z += Z y`` over the nodes' group tables.

A group's mode ``c`` at a node whose offset from the group's centre over its radius of gyration is ``y``: the
translations ``e_c`` (``c < 3``), then the rotations ``e_k x y`` (rigid, ``c = 3 + k``) or the affine motions
``e_r y_l`` (affine, ``c = 3 + 3 r + l``); each weighed by the group's share of the node's mass."""

from typing import Any

import warp as wp

from . import explicit_kernels as kernels

__all__ = ["mode_vector", "mode_coefficient", "group_velocity", "node_offset", "particle_stencils", "restrict_nodes",
           "prolong_nodes"]

# forward kernels only, no adjoints to compile (why: warpmpm.solvers.explicit_kernels)
wp.set_module_options({"enable_backward": False})


@wp.func
def mode_vector(y: wp.vec3, c: int, affine: int):
    """Mode ``c`` of a group at scaled offset ``y`` (module docstring)."""
    if c < 3:
        e = wp.vec3(0.0)
        e[c] = 1.0
        return e
    if affine == 0:
        e = wp.vec3(0.0)
        e[c - 3] = 1.0
        return wp.cross(e, y)
    r = (c - 3) // 3
    out = wp.vec3(0.0)
    out[r] = y[(c - 3) - 3 * r]
    return out


@wp.func
def mode_coefficient(t: wp.vec3, y: wp.vec3, c: int, affine: int):
    """``Z_c . t`` at one node: what a nodal vector ``t`` (already weighed by the group's share) gives mode ``c``."""
    if c < 3:
        return t[c]
    if affine == 0:
        return wp.cross(y, t)[c - 3]
    r = (c - 3) // 3
    return t[r] * y[(c - 3) - 3 * r]


@wp.func
def group_velocity(coef: wp.array(dtype=Any), b: int, y: wp.vec3, affine: int):
    """``sum_c coef[b + c] Z_c(y)``: a group's coarse motion (its ``6`` or ``12`` coefficients from ``b``) at a node."""
    v = wp.vec3(0.0)
    for c in range(6 + 6 * affine):
        v += float(coef[b + c]) * mode_vector(y, c, affine)
    return v


@wp.func
def node_offset(n: int, ny: int, nz: int, dx: float, centre: wp.vec3, inv_len: float):
    """Node ``n``'s (flat index ``(i ny + j) nz + k``) offset from a group's centre over its radius of gyration."""
    xi = wp.vec3(float(n // (ny * nz)), float((n // nz) % ny), float(n % nz)) * dx
    return (xi - centre) * inv_len


@wp.kernel
def particle_stencils(x: wp.array(dtype=wp.vec3), dx: float, ny: int, nz: int, flat: wp.array(dtype=int, ndim=2),
                      w: wp.array(dtype=float, ndim=2), r: wp.array(dtype=wp.vec3, ndim=2)):
    """Each particle's 27 stencil nodes (flat index), B-spline weights and offsets ``x_i - x_p`` (m): the stencil of
    P2G and G2P (:func:`warpmpm.solvers.explicit_kernels.stencil`), for the coarse space's host code."""
    p = wp.tid()
    inv_dx = 1.0 / dx
    base, fx, wx, wy, wz = kernels.stencil(x[p], inv_dx)
    q = int(0)
    for a in range(3):
        for b in range(3):
            for cc in range(3):
                flat[p, q] = ((base[0] + a) * ny + base[1] + b) * nz + base[2] + cc
                w[p, q] = wx[a] * wy[b] * wz[cc]
                r[p, q] = (wp.vec3(float(a), float(b), float(cc)) - fx) * dx
                q += 1


@wp.kernel
def restrict_nodes(nodes: wp.array(dtype=int), node_group: wp.array(dtype=int, ndim=2), node_share: wp.array(dtype=float, ndim=2),
                   centre: wp.array(dtype=wp.vec3), inv_len: wp.array(dtype=float), v: wp.array(dtype=wp.vec3), ny: int, nz: int,
                   dx: float, affine: int, t: wp.array(dtype=wp.float64)):
    """``t += Z^T v`` over the active nodes (one thread a node; ``v`` a flat nodal vector array)."""
    a = wp.tid()
    n = nodes[a]
    vi = v[n]
    stride = 6 + 6 * affine
    for q in range(node_share.shape[1]):
        s = node_share[a, q]
        if s > 0.0:
            g = node_group[a, q]
            y = node_offset(n, ny, nz, dx, centre[g], inv_len[g])
            for c in range(stride):
                wp.atomic_add(t, stride * g + c, wp.float64(mode_coefficient(s * vi, y, c, affine)))


@wp.kernel
def prolong_nodes(nodes: wp.array(dtype=int), node_group: wp.array(dtype=int, ndim=2), node_share: wp.array(dtype=float, ndim=2),
                  centre: wp.array(dtype=wp.vec3), inv_len: wp.array(dtype=float), y: wp.array(dtype=wp.float64), ny: int, nz: int,
                  dx: float, affine: int, z: wp.array(dtype=wp.vec3)):
    """``z += Z y`` over the active nodes (one thread a node; ``z`` a flat nodal vector array)."""
    a = wp.tid()
    n = nodes[a]
    stride = 6 + 6 * affine
    acc = wp.vec3(0.0)
    for q in range(node_share.shape[1]):
        s = node_share[a, q]
        if s > 0.0:
            g = node_group[a, q]
            acc += s * group_velocity(y, stride * g, node_offset(n, ny, nz, dx, centre[g], inv_len[g]), affine)
    z[n] = z[n] + acc
