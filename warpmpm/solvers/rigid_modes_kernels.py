"""Kernels of the rigid-mode acceleration (:mod:`warpmpm.solvers.rigid_modes`): restricting the force to the groups'
motions, the boosted coarse modes' projection and expansion, the guard, prolonging the velocity change."""

import warp as wp

from .coarse_space_kernels import group_velocity, mode_coefficient, node_offset

__all__ = ["SLOTS", "node_ijk", "restrict_force", "reduce_slots", "coarse_project", "coarse_expand", "coarse_guard",
           "prolong_velocity", "energy_blocks"]

# forward kernels only, no adjoints to compile (why: warpmpm.solvers.explicit_kernels)
wp.set_module_options({"enable_backward": False})

#: slots the coarse force is spread over (by node), then summed (a GPU would otherwise queue every node's atomics on
#: the same few addresses)
SLOTS = 64


@wp.func
def node_ijk(n: int, ny: int, nz: int):
    """Grid indices of the node with flat index ``n`` (``(i ny + j) nz + k``)."""
    return wp.vec3i(n // (ny * nz), (n // nz) % ny, n % nz)


@wp.kernel
def restrict_force(nodes: wp.array(dtype=int), node_group: wp.array(dtype=int, ndim=2), node_share: wp.array(dtype=float, ndim=2),
                   centre: wp.array(dtype=wp.vec3), inv_len: wp.array(dtype=float), force_sum: wp.array(dtype=wp.vec3, ndim=3),
                   dx: float, affine: int, first: int, slot0: int, slots: wp.array(dtype=float, ndim=2)):
    """``g = Z^T f``: each group's share of the nodal force impulse as a net force (3) and either a torque about its
    centre (3, ``affine`` 0) or the force's first moment ``f y^T`` (9, ``affine`` 1), ``y`` the node's offset from the
    centre over the group's radius of gyration; into ``slots[stride g + c, slot0 + node % SLOTS]``. One thread an
    active node, from node ``first`` on (a launch per CPU thread over its own band of ``SLOTS`` slots)."""
    a = first + wp.tid()
    n = nodes[a]
    ny = force_sum.shape[1]
    nz = force_sum.shape[2]
    ijk = node_ijk(n, ny, nz)
    f = force_sum[ijk[0], ijk[1], ijk[2]]
    slot = slot0 + a % SLOTS
    stride = 6 + 6 * affine
    for q in range(node_share.shape[1]):
        s = node_share[a, q]
        if s > 0.0:
            g = node_group[a, q]
            y = node_offset(n, ny, nz, dx, centre[g], inv_len[g])
            for c in range(stride):
                wp.atomic_add(slots, stride * g + c, slot, mode_coefficient(s * f, y, c, affine))


@wp.kernel
def reduce_slots(slots: wp.array(dtype=float, ndim=2), g: wp.array(dtype=float)):
    """``g[l]`` = the sum of row ``l`` of the slots (cleared for the next step); one thread a coarse mode."""
    l = wp.tid()
    acc = float(0.0)
    for s in range(slots.shape[1]):
        acc += slots[l, s]
        slots[l, s] = 0.0
    g[l] = acc


@wp.kernel
def coarse_project(WT: wp.array(dtype=float, ndim=2), boost: wp.array(dtype=float), g: wp.array(dtype=float), first: int,
                   h: wp.array(dtype=float)):
    """``h_j = (beta_j - 1) phi_j . g`` for the boosted mode ``j = first + tid`` (``WT``'s row ``j`` is ``phi_j``)."""
    j = first + wp.tid()
    acc = float(0.0)
    for l in range(WT.shape[1]):
        acc += WT[j, l] * g[l]
    h[j] = boost[j] * acc


@wp.kernel
def coarse_expand(W: wp.array(dtype=float, ndim=2), h: wp.array(dtype=float), n_boosted: int, first: int,
                  y: wp.array(dtype=float)):
    """``y_l = sum_j W[l, j] h_j`` over the ``n_boosted`` boosted modes, for row ``l = first + tid``: with
    :func:`coarse_project`, ``y = B g`` with ``B = Phi_b diag(beta - 1) Phi_b^T`` (the unboosted modes add nothing)."""
    l = first + wp.tid()
    acc = float(0.0)
    for j in range(n_boosted):
        acc += W[l, j] * h[j]
    y[l] = acc


@wp.kernel
def coarse_guard(y: wp.array(dtype=float), guard: wp.array(dtype=float), growth: float, steps: float):
    """One thread: ``guard = [last max |y|, steps in a row it grew by more than growth, enabled (1 or 0), step of the
    switch-off]``; turns ``enabled`` to 0 when the growth has held ``steps`` steps."""
    m = float(0.0)
    for j in range(y.shape[0]):
        m = wp.max(m, wp.abs(y[j]))
    if m > growth * guard[0] and guard[0] > 0.0:
        guard[1] = guard[1] + 1.0
    else:
        guard[1] = 0.0
    guard[0] = m
    guard[4] = guard[4] + 1.0
    if guard[1] >= steps and guard[2] > 0.0:
        guard[2] = 0.0
        guard[3] = guard[4]


@wp.kernel
def prolong_velocity(nodes: wp.array(dtype=int), node_group: wp.array(dtype=int, ndim=2), node_share: wp.array(dtype=float, ndim=2),
                     centre: wp.array(dtype=wp.vec3), inv_len: wp.array(dtype=float), y: wp.array(dtype=float),
                     damping: wp.array(dtype=float), dx: float, affine: int, guard: wp.array(dtype=float), first: int,
                     grid_v: wp.array(dtype=wp.vec4, ndim=3)):
    """``v += damping Z y``: each group's share of its boosted rigid (or affine) velocity change at active node
    ``first + tid`` (none once :func:`coarse_guard` has switched the correction off)."""
    a = first + wp.tid()
    if guard[2] == 0.0:
        return
    n = nodes[a]
    ny = grid_v.shape[1]
    nz = grid_v.shape[2]
    ijk = node_ijk(n, ny, nz)
    dv = wp.vec3(0.0)
    hit = int(0)
    stride = 6 + 6 * affine
    for q in range(node_share.shape[1]):
        s = node_share[a, q]
        if s > 0.0:
            g = node_group[a, q]
            dv += s * group_velocity(y, stride * g, node_offset(n, ny, nz, dx, centre[g], inv_len[g]), affine)
            hit = 1
    if hit != 0:
        dv = damping[0] * dv
        grid_v[ijk[0], ijk[1], ijk[2]] = grid_v[ijk[0], ijk[1], ijk[2]] + wp.vec4(dv[0], dv[1], dv[2], 0.0)


@wp.kernel
def energy_blocks(starts: wp.array(dtype=int), counts: wp.array(dtype=int), order: wp.array(dtype=int),
                  group: wp.array(dtype=int), Q: wp.array(dtype=wp.float64, ndim=3), stride: int, first: int,
                  U: wp.array(dtype=wp.float64, ndim=2)):
    """``U += Q_p^T Q_p``, upper blocks only, for particle ``first + tid``: over every pair ``i <= j`` of its
    (particle, group) entries (sorted by group, so the second group is the larger), the ``stride x stride`` block
    ``sum_r Q[e1, r, a] Q[e2, r, b]`` at the two groups' modes. ``E = U + U^T`` less the diagonal blocks once
    (:meth:`RigidModeAccelerator._sum_energy_blocks`). One thread a particle; ``Q`` (entries, 10, stride): the square
    root of each entry's elastic and drive energy (:meth:`RigidModeAccelerator.coarse_matrices`)."""
    p = first + wp.tid()
    s0 = starts[p]
    c = counts[p]
    for i in range(c):
        e1 = order[s0 + i]
        r1 = group[e1] * stride
        for j in range(i, c):
            e2 = order[s0 + j]
            r2 = group[e2] * stride
            for a in range(stride):
                for b in range(stride):
                    acc = wp.float64(0.0)
                    for r in range(Q.shape[1]):
                        acc += Q[e1, r, a] * Q[e2, r, b]
                    wp.atomic_add(U, r1 + a, r2 + b, acc)
