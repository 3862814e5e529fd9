"""Time per MPM step and particle-steps per second, warpmpm vs an independent Taichi MLS-MPM step.

The scene is a stiff two-material cube (half pancreas, half duodenum: ~3000x stiffness contrast),
1 mm particle spacing, pre-compressed 5 % so every particle takes the SVD path. Both solvers use
the same particle count, grid cell size (4 particles per cell), time step and fixed-corotated
model; Taichi's step is written here independently (benchmark-only dependency: ``pip install
taichi``). Run::

    python benchmarks/solver_step.py                 # 10k, 100k, 300k, 1M on this machine's default device
    python benchmarks/solver_step.py --sizes 10000 --device cpu --steps 20

Prints a table (ms per step, M particle-steps/s, Taichi/warpmpm ratio, bytes per particle). On the CPU warpmpm
is timed twice in the same run, on one thread and split over ``--threads`` (default 2: warpmpm.solvers.parallel); the
ratio to Taichi (which uses every core) is for the split step, and the split step's gain over one thread is
its own column.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


from warpmpm.experiment import raw_numbers as raw

import warp as wp

from warpmpm.scenes import block_model, merge_models
from warpmpm.solvers import ExplicitConfig, MPMModel, MPMSolver, SolverConfig


def scene(n_target: int):
    side = int(round(n_target ** (1 / 3)))
    half = side // 2
    a = block_model((half, side, side), (1.0, 1.0, 1.0), "pancreas")
    b = block_model((side - half, side, side), (1.0, 1.0, 1.0), "duodenum", origin_mm=(float(half), 0.0, 0.0))
    return merge_models(a, b)


def bytes_per_particle(m: MPMModel, s: MPMSolver, states) -> float:
    total = 0
    for arr in [m.mass, m.vol0, m.mu, m.lam, s.zero_force] + [getattr(st, n) for st in states for n in ("x", "v", "C", "F")]:
        total += arr.capacity
    scatter = s.grid_m.capacity + s.grid_mv.capacity if s.fields else s.grid_mm.capacity
    grid = scatter + s.grid_v.capacity
    return total / m.n, grid


def time_warp(pm, device: str, steps: int, threads: int | None = None):
    m = MPMModel(pm, SolverConfig(device=device, cpu_threads=threads, explicit=ExplicitConfig(check_every=10**9)))  # no NaN read-back in the timed steps
    s = MPMSolver(m)
    a, b = m.state(), m.state()
    F0 = np.diag([0.95, 1.0, 1.0]).astype(np.float32)
    a.F.assign(np.tile(F0, (pm.n, 1, 1)))
    for _ in range(3):  # warm up (compile, caches)
        s.step(a, b)
        a, b = b, a
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        s.step(a, b)
        a, b = b, a
    wp.synchronize_device(device)
    dt = (time.perf_counter() - t0) / steps
    s.check()
    bpp, grid = bytes_per_particle(m, s, (a, b))
    return dt, m, bpp, grid


def time_taichi(pm, m: MPMModel, steps: int, arch: str):
    import taichi as ti

    ti.init(arch=ti.gpu if arch == "cuda" else ti.cpu, default_fp=ti.f32, offline_cache=True, log_level=ti.WARN)
    n = pm.n
    nx, ny, nz = m.grid_shape
    dx = m.dx_mm * 1e-3
    inv_dx = 1.0 / dx
    dt = m.dt_s
    x = ti.Vector.field(3, ti.f32, n)
    v = ti.Vector.field(3, ti.f32, n)
    C = ti.Matrix.field(3, 3, ti.f32, n)
    F = ti.Matrix.field(3, 3, ti.f32, n)
    mass = ti.field(ti.f32, n)
    vol = ti.field(ti.f32, n)
    mu = ti.field(ti.f32, n)
    lam = ti.field(ti.f32, n)
    gm = ti.field(ti.f32, (nx, ny, nz))
    gv = ti.Vector.field(3, ti.f32, (nx, ny, nz))
    x.from_numpy(m.to_local_m(pm.positions_mm))
    mass.from_numpy(m.mass.numpy())
    vol.from_numpy(m.vol0.numpy())
    mu.from_numpy(m.mu.numpy())
    lam.from_numpy(m.lam.numpy())
    F.from_numpy(np.tile(np.diag([0.95, 1.0, 1.0]).astype(np.float32), (n, 1, 1)))
    damping = float(np.exp(-m.damping_per_s * dt))

    @ti.kernel
    def step():
        for I in ti.grouped(gm):
            gm[I] = 0.0
            gv[I] = ti.Vector([0.0, 0.0, 0.0])
        for p in x:
            base = (x[p] * inv_dx - 0.5).cast(int)
            fx = x[p] * inv_dx - base.cast(float)
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            U, sig, V = ti.svd(F[p])
            J = F[p].determinant()
            R = U @ V.transpose()
            tau = 2 * mu[p] * (F[p] - R) @ F[p].transpose() + ti.Matrix.identity(float, 3) * lam[p] * J * (J - 1)
            affine = -dt * vol[p] * 4 * inv_dx * inv_dx * tau + mass[p] * C[p]
            for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                off = ti.Vector([i, j, k])
                dpos = (off.cast(float) - fx) * dx
                wt = w[i][0] * w[j][1] * w[k][2]
                gv[base + off] += wt * (mass[p] * v[p] + affine @ dpos)
                gm[base + off] += wt * mass[p]
        for I in ti.grouped(gm):
            if gm[I] > 0:
                gv[I] = gv[I] / gm[I] * damping
        for p in x:
            base = (x[p] * inv_dx - 0.5).cast(int)
            fx = x[p] * inv_dx - base.cast(float)
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v = ti.Vector.zero(float, 3)
            new_C = ti.Matrix.zero(float, 3, 3)
            for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                dpos = ti.Vector([i, j, k]).cast(float) - fx
                g = gv[base + ti.Vector([i, j, k])]
                wt = w[i][0] * w[j][1] * w[k][2]
                new_v += wt * g
                new_C += 4 * inv_dx * wt * g.outer_product(dpos)
            v[p] = new_v
            C[p] = new_C
            x[p] += dt * new_v
            F[p] = (ti.Matrix.identity(float, 3) + dt * new_C) @ F[p]

    for _ in range(3):
        step()
    ti.sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    ti.sync()
    out = (time.perf_counter() - t0) / steps
    ti.reset()
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default="10000,100000,300000,1000000")
    p.add_argument("--device", default=None, help="cpu or cuda (default: CUDA when available)")
    p.add_argument("--steps", type=int, default=0, help="timed steps (default: enough for ~3 s, at least 5)")
    p.add_argument("--no-taichi", action="store_true")
    p.add_argument("--threads", type=int, default=2, help="threads of warpmpm's split CPU step (timed beside one thread)")
    p.add_argument("--runs", type=int, default=1, help="repeat the whole measurement this many times (the issue's figure: the "
                   "median of five runs' ratios)")
    p.add_argument("--raw", type=raw.check_name, default="default", help="the run's name in benchmarks/results/solver_step.json")
    a = p.parse_args(argv)
    wp.config.log_level = wp.LOG_ERROR  # no init banner or module-load lines
    wp.init()
    device = a.device or ("cuda" if wp.is_cuda_available() else "cpu")
    name = wp.get_device(device).name
    print(f"device: {device} ({name}), warp {wp.__version__}, cores {os.cpu_count()}")
    runs = []
    for run in range(max(1, a.runs)):
        rows = []
        for n in [int(s) for s in a.sizes.split(",")]:
            pm = scene(n)
            steps = a.steps or (200 if device.startswith("cuda") else max(5, int(3e6 / pm.n)))
            t_1 = float("nan")
            if not device.startswith("cuda"):
                t_1, *_ = time_warp(pm, device, steps, 1)
            t_w, m, bpp, grid = time_warp(pm, device, steps, a.threads)
            t_t = float("nan")
            if not a.no_taichi:
                try:
                    t_t = time_taichi(pm, m, steps, device)
                except Exception as exc:  # benchmark-only dependency
                    print(f"taichi unavailable: {exc}")
                    a.no_taichi = True
            rows.append((pm.n, m.grid_shape, t_1, t_w, t_t, bpp, grid))
            print(f"  run {run + 1}, {pm.n} particles: warpmpm {t_1 * 1e3:.3f} ms/step on one thread, {t_w * 1e3:.3f} split over "
                  f"{a.threads}, taichi {t_t * 1e3:.3f} ms/step", flush=True)
        print()
        print(f"| particles | grid | warpmpm 1 thread ms/step | warpmpm {a.threads} threads ms/step | {a.threads} threads / 1 (speed) | "
              "M particle-steps/s | taichi ms/step | taichi / warpmpm | bytes/particle | grid MB |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for n, g, t1, tw, tt, bpp, grid in rows:
            print(f"| {n} | {g[0]}x{g[1]}x{g[2]} | {t1 * 1e3:.3f} | {tw * 1e3:.3f} | {t1 / tw:.2f} | {n / tw / 1e6:.2f} | {tt * 1e3:.3f} | "
                  f"{tt / tw:.2f} | {bpp:.0f} | {grid / 1e6:.1f} |")
        runs.append([{"particles": n, "grid": list(g), "threads": a.threads, "warpmpm_1_thread_s_per_step": t1,
                      "warpmpm_s_per_step": tw, "taichi_s_per_step": tt, "bytes_per_particle": bpp, "grid_bytes": grid}
                     for n, g, t1, tw, tt, bpp, grid in rows])
    if len(runs) > 1:
        print()
        print(f"| particles | taichi / warpmpm ({a.threads} threads), {len(runs)} runs | median | taichi / warpmpm (1 thread), median | "
              f"{a.threads} threads / 1, median |")
        print("|---|---|---|---|---|")
        for i, r in enumerate(runs[0]):
            ratios = [run[i]["taichi_s_per_step"] / run[i]["warpmpm_s_per_step"] for run in runs]
            one = [run[i]["taichi_s_per_step"] / run[i]["warpmpm_1_thread_s_per_step"] for run in runs]
            gain = [run[i]["warpmpm_1_thread_s_per_step"] / run[i]["warpmpm_s_per_step"] for run in runs]
            print(f"| {r['particles']} | {', '.join(f'{x:.2f}' for x in ratios)} | **{np.median(ratios):.2f}** | {np.median(one):.2f} | "
                  f"{np.median(gain):.2f} |")
    raw.save(__file__, runs[0] if len(runs) == 1 else runs, run=a.raw)


if __name__ == "__main__":
    main()
