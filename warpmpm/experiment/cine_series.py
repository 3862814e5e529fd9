"""A synthetic but scanner-like cine series with its 3D truth, and the evaluation of a track against it.

:func:`make_cine` moves the organs of a planning case as breathing does (superior-inferior and
anterior-posterior, a different amplitude per organ and per cycle) with a slow aperiodic push of the
duodenum (or stomach) toward the pancreas; the pancreas itself is not driven, it moves through contact.
Each frame's truth is simulated from the planning state with perturbed materials (as the GT protocols
do); the frame is that state's image (the planning image warped by the truth) on a sagittal and/or
coronal plane through the pancreas, averaged over the slice thickness (partial volume), resampled to
the scanner's in-plane pixel (2 mm by default), with noise, written as a 2D MR DICOM file (default) or a
NIfTI image one voxel thick in its 3D geometry. The truth goes to ``truth/``, the frames to ``cine/``;
the tracker never reads ``truth/``.

:func:`evaluate_track` scores a tracker's output against that truth beside ``initial`` (no motion) and
``propagate`` (each frame's slice motion copied to every particle).
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import SimpleITK as sitk

from ..errors import InputError, strict_json
from ..groundtruth import perturb_materials, simulate_gt
from ..imaging import warp_image
from ..images import ORGANS, Case, Geometry
from ..metrics import dice, voxelize
from ..model import build_model
from ..slices import orientation_image_axis

__all__ = ["MAX_FRAMES", "BREATHING_MM", "check_cine_parameters", "make_cine", "plane_positions", "same_session", "slab_average", "evaluate_track",
           "plot_track_errors"]

#: Most frames a synthetic series may hold (10 minutes at 10 frames/s).
MAX_FRAMES = 6000

#: Breathing amplitudes (mm): superior-inferior, anterior-posterior, per organ.
BREATHING_MM = {"pancreas": (10.0, 3.0), "stomach": (12.0, 4.0), "duodenum": (10.0, 3.0), "left_kidney": (14.0, 3.0)}


def check_cine_parameters(planes, frames: int, fps: float, period_s: float, thickness_mm: float, pixel_mm: float | None,
                          fmt: str) -> None:
    """:class:`InputError` naming the first bad parameter of :func:`make_cine` (checked before anything is written)."""
    for p in planes:
        if p not in ("sagittal", "coronal", "axial"):
            raise InputError(f"unknown plane {p!r}; use sagittal, coronal or axial")
    if not planes:
        raise InputError("no cine plane given; use sagittal, coronal or axial")
    if fmt not in ("nifti", "dicom"):
        raise InputError(f"unknown frame format {fmt!r}; use nifti or dicom")
    if not (isinstance(frames, int) and 1 <= frames <= MAX_FRAMES):
        raise InputError(f"--frames must be a whole number in 1..{MAX_FRAMES}, got {frames!r}")
    for name, v, lo, hi in (("--fps", fps, 0.1, 100.0), ("breathing period", period_s, 0.5, 60.0),
                            ("--thickness-mm", thickness_mm, 0.5, 30.0)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
            raise InputError(f"{name} must be a finite number in {lo}..{hi}, got {v!r}")
    if pixel_mm is not None and not (math.isfinite(pixel_mm) and 0.2 <= pixel_mm <= 10.0):
        raise InputError(f"cine pixel size must be 0.2-10 mm, got {pixel_mm}")


def make_cine(case: Case, out_dir: str, *, planes=("sagittal",), frames: int = 8, fps: float = 4.0, period_s: float = 4.0,
              thickness_mm: float = 6.0, pixel_mm: float | None = 2.0, noise_sd: float = 0.02, push_mm: float = 4.0,
              particle_step: int = 1, seed: int = 0, fmt: str = "dicom", truth_fields: list[str] | None = None,
              slices: dict | None = None, progress=None) -> dict:
    """Write ``out_dir/cine`` (frames) and ``out_dir/truth`` (positions, label maps) for ``case``; returns the
    series' parameters (also in ``truth/series.json``). Frames cycle through ``planes``; each is averaged over
    ``thickness_mm`` (partial volume) and resampled to ``pixel_mm`` square pixels in plane (an MR-Linac's
    cine: 1.5-2.5 mm; None keeps the planning grid's). ``fmt``: ``dicom`` (default: 2D MR DICOM, 16-bit, with
    position, orientation, acquisition time, instance number and slice thickness) or ``nifti`` (one voxel
    thick).

    ``truth_fields``: the truth as displacement fields on the planning grid, one file a frame (:mod:`warpmpm.fields`,
    e.g. ``warpmpm make-truth``'s ``fields/``): each frame's particles move by its field and the frame is the planning
    image warped by it; ``frames`` is then the number of fields, and no motion is simulated.

    ``slices``: orientation -> the index of the planning volume's slice each plane images (what ``warpmpm plan-planes``
    chose, or what the MR-Linac was set to); an orientation it does not name lies where it shows the largest section of
    the pancreas (a plane through the centroid can miss a curved pancreas: on the CT sample the sagittal plane through it
    crosses 3 of its voxels)."""
    if truth_fields is not None:
        frames = len(truth_fields)
        if frames == 0:
            raise InputError("--truth holds no field (frame_NNNN.nii.gz)")
    check_cine_parameters(planes, frames, fps, period_s, thickness_mm, pixel_mm, fmt)
    if case.image is None:
        raise InputError("a synthetic cine series needs the planning image")
    present = tuple(o for o in ORGANS if o in case.label_map and np.any(case.labels == case.label_map[o]))
    model = build_model(case, present, sampling_step=particle_step)
    neighbours = [o for o in present if o != "pancreas"]
    if not neighbours:
        raise InputError("a synthetic cine series needs a neighbour of the pancreas to drive (stomach, duodenum or left kidney)")
    rng = np.random.default_rng(seed)
    cycles = int(math.ceil(frames / fps / period_s)) + 1
    cycle_amp = rng.uniform(0.7, 1.3, cycles)
    pusher = "duodenum" if "duodenum" in present else neighbours[0]
    pan_c = model.positions_mm[model.organ_slice("pancreas")].mean(0)
    through = plane_positions(case, model, planes, slices)
    push_dir = pan_c - model.positions_mm[model.organ_slice(pusher)].mean(0)
    push_dir /= max(np.linalg.norm(push_dir), 1e-9)
    g = case.geometry
    cine, truth = os.path.join(out_dir, "cine"), os.path.join(out_dir, "truth")
    os.makedirs(cine, exist_ok=True)
    os.makedirs(os.path.join(truth, "labels"), exist_ok=True)
    driven = np.nonzero(model.organ_index != model.organs.index("pancreas"))[0]
    all_truth = []
    organ_mask = np.isin(case.labels, [case.label_map[o] for o in present])
    if truth_fields is not None:  # every field checked before anything is written
        from ..fields import read_field

        for path in truth_fields:
            read_field(path, g, organ_mask)
    for k in range(frames):
        t = k / fps
        phase = (1.0 - math.cos(2 * math.pi * t / period_s)) / 2.0
        amp = cycle_amp[int(t // period_s)]
        target = model.positions_mm.copy()
        for o in neighbours:
            si, ap = BREATHING_MM[o]
            sel = model.organ_slice(o)
            target[sel] += amp * phase * np.array([0.0, ap, -si])  # exhale to inhale: inferior and anterior (LPS)
        target[model.organ_slice(pusher)] += push_mm * (k / max(frames - 1, 1)) * push_dir
        if truth_fields is None:
            _, res = simulate_gt(model, driven, target[driven], perturb=True, seed=seed + 7, solver_config=None, device="cpu")
            pos, how = res.positions_mm, f"truth in {res.steps} steps"
            warped = warp_image(case, model, pos)
        else:
            from ..fields import read_field, sample_field, warp_volume

            field = read_field(truth_fields[k], g)
            pos, how = model.positions_mm + sample_field(field, g, model.positions_mm), f"truth {os.path.basename(truth_fields[k])}"
            warped = warp_volume(case.image, field, g)
        all_truth.append(pos)
        orientation = planes[k % len(planes)]
        frame = _frame_image(warped, case, orientation, through[orientation], thickness_mm, noise_sd * float(np.ptp(case.image)), rng, pixel_mm)
        if fmt == "nifti":
            sitk.WriteImage(frame, os.path.join(cine, f"frame_{k:04d}_{orientation}.nii.gz"))
        else:
            if k == 0:
                from pydicom.uid import generate_uid

                uids = {"0020|000d": generate_uid(), "0020|000e": generate_uid(), "0020|0052": generate_uid()}
            _write_dicom_frame(frame, os.path.join(cine, f"frame_{k:04d}.dcm"), k, t, thickness_mm, case.image, uids)
        from ..imaging import particle_label_map

        lab = particle_label_map(model, pos, {o: case.label_map[o] for o in model.organs})
        sitk.WriteImage(g.apply_to(sitk.GetImageFromArray(lab.astype(np.uint8))), os.path.join(truth, "labels", f"frame_{k:04d}.nii.gz"))
        if progress:
            progress(f"frame {k} ({orientation}, t {t:.2f} s): {how}, pancreas moved "
                     f"{np.linalg.norm(pos[model.organ_slice('pancreas')].mean(0) - pan_c):.2f} mm")
    np.savez_compressed(os.path.join(truth, "positions.npz"), planning_mm=model.positions_mm, organ_index=model.organ_index,
                        organs=np.asarray(model.organs), truth_mm=np.asarray(all_truth))
    params = {"frames": frames, "fps": fps, "period_s": period_s, "planes": list(planes), "thickness_mm": thickness_mm,
              "slices": {o: int(np.rint(g.world_to_index(through[o][None, :])[0][orientation_image_axis(g, o)])) for o in planes},
              "placement": {o: "given" if slices and o in slices else "largest section of the pancreas" for o in planes},
              "pixel_mm": pixel_mm, "format": fmt,
              "noise_sd": noise_sd, "push_mm": push_mm, "pusher": pusher, "particle_step": particle_step, "seed": seed,
              "breathing_mm": BREATHING_MM, "cycle_amplitude": cycle_amp.tolist(), "materials": {
                  o: {"lam_pa": m.lam_pa, "mu_pa": m.mu_pa} for o, m in perturb_materials(model.materials, seed + 7).items()}}
    if truth_fields is not None:  # the motion came from the fields, not from the breathing and push above
        params = {k: v for k, v in params.items() if k not in ("push_mm", "pusher", "breathing_mm", "cycle_amplitude", "materials")}
        params["truth_fields"] = [os.path.abspath(p) for p in truth_fields]
    with open(os.path.join(truth, "series.json"), "w") as f:
        json.dump(strict_json(params), f, indent=1, allow_nan=False)
    return params


def same_session(cine_folder: str, ref) -> None:
    """Give a synthetic DICOM cine (``make-cine``) the frame of reference and patient ID of the planning series ``ref``
    (a :class:`warpmpm.dicom_rt.SeriesReference`) written from the same planning image afterwards, as the cine of the
    session a planning MR was taken in carries them: the tracker refuses a cine of another frame of reference or
    patient. For synthetic series only; a clinic's cine keeps what the scanner wrote."""
    import pydicom

    for name in sorted(os.listdir(cine_folder)):
        if not name.lower().endswith(".dcm"):
            continue
        path = os.path.join(cine_folder, name)
        ds = pydicom.dcmread(path)
        ds.FrameOfReferenceUID, ds.PatientID = ref.frame_of_reference_uid, ref.patient_id
        ds.save_as(path)


def _write_dicom_frame(frame: sitk.Image, path: str, k: int, t: float, thickness_mm: float, planning: np.ndarray,
                       uids: dict | None = None) -> None:
    """A frame as a 2D MR DICOM file: the thin axis last (so the writer's position and orientation place the
    plane), intensities mapped linearly to 0..4000 with the planning image's range (16-bit), acquisition time
    ``t`` seconds after 10:00:00, instance number ``k + 1``; ``uids``: the series' study, series and frame of reference
    UIDs (one session, as a scanner writes them), patient ID WARPMPM-SYNTHETIC."""
    thin = [a for a in range(3) if frame.GetSize()[a] == 1][0]
    order = [a for a in range(3) if a != thin] + [thin]
    img = sitk.PermuteAxes(frame, order)
    lo, hi = float(np.min(planning)), float(np.max(planning))
    arr = np.clip((sitk.GetArrayFromImage(img) - lo) / max(hi - lo, 1e-9) * 4000.0, 0, 32000)
    out = sitk.GetImageFromArray(np.rint(arr).astype(np.int16))
    out.CopyInformation(img)
    hh, rest = divmod(10 * 3600 + t, 3600)
    mm, ss = divmod(rest, 60)
    for tag, value in {"0008|0060": "MR", "0008|0032": f"{int(hh):02d}{int(mm):02d}{ss:09.6f}", "0020|0013": str(k + 1),
                       "0018|0050": f"{thickness_mm:.3f}", "0010|0020": "WARPMPM-SYNTHETIC", **(uids or {})}.items():
        out.SetMetaData(tag, value)
    w = sitk.ImageFileWriter()
    w.KeepOriginalImageUIDOn()
    w.SetFileName(path)
    w.Execute(out)


def plane_positions(case: Case, model, planes, slices: dict | None = None) -> dict:
    """orientation -> a world point (mm) its plane passes through: the slice ``slices`` names (planning-volume index), else
    the slice with the most pancreas particles (its largest section), both through the pancreas centroid in plane."""
    g = case.geometry
    centre = g.world_to_index(model.positions_mm[model.organ_slice("pancreas")].mean(0)[None, :])[0]
    out = {}
    for o in planes:
        a = orientation_image_axis(g, o)
        ijk = centre.copy()
        if slices and o in slices:
            k = int(slices[o])
            if not 0 <= k < g.size[a]:
                raise InputError(f"--slices {o}:{k} is outside the planning volume (valid 0..{g.size[a] - 1})")
        else:
            k = int(np.argmax(model.slice_counts(o)[:, model.organs.index("pancreas")]))
        ijk[a] = k
        out[o] = g.index_to_world(ijk[None, :])[0]
    return out


def slab_average(volume: np.ndarray, np_axis: int, k: int, thickness_voxels: float) -> np.ndarray:
    """``volume`` averaged along ``np_axis`` over a box ``thickness_voxels`` wide centred on index ``k`` (a
    rectangular slice profile): each voxel weighs by the share of it inside the box, so a 6 mm slice on a 3 mm
    grid is half the centre voxel and a quarter of each neighbour (before, whole voxels were averaged and the
    rounding made it the centre voxel alone: 3 mm). Voxels beyond the volume's edge are left out (the weights
    renormalised). Returns the average with ``np_axis`` kept, one voxel thick."""
    half = thickness_voxels / 2.0
    lo, hi = int(math.floor(k - half + 0.5)), int(math.ceil(k + half - 0.5))
    js = np.arange(max(lo, 0), min(hi, volume.shape[np_axis] - 1) + 1)
    w = np.clip(np.minimum(js + 0.5, k + half) - np.maximum(js - 0.5, k - half), 0.0, None)
    w = w / w.sum()
    part = np.take(volume, js, axis=np_axis).astype(np.float64)
    shape = [1, 1, 1]
    shape[np_axis] = len(js)
    return (part * w.reshape(shape)).sum(axis=np_axis, keepdims=True).astype(np.float32)


def _frame_image(volume: np.ndarray, case: Case, orientation: str, through_mm: np.ndarray, thickness_mm: float, noise: float,
                 rng, pixel_mm: float | None = None) -> sitk.Image:
    """The plane of ``orientation`` through ``through_mm``, averaged over ``thickness_mm``, one voxel thick,
    resampled (linear) to ``pixel_mm`` pixels in plane over the same field of view; noise added last, at the
    scanner's pixels."""
    g = case.geometry
    a = orientation_image_axis(g, orientation)
    k = int(np.rint(g.world_to_index(through_mm[None, :])[0][a]))
    plane = slab_average(volume, 2 - a, k, thickness_mm / g.spacing_mm[a])
    start = [0, 0, 0]
    start[a] = k
    origin = g.index_to_world(np.asarray(start, dtype=np.float64)[None, :])[0]
    spacing = list(g.spacing_mm)
    spacing[a] = float(thickness_mm)
    img = sitk.GetImageFromArray(plane)
    img.SetOrigin(tuple(float(v) for v in origin))
    img.SetSpacing(tuple(spacing))
    img.SetDirection(g.direction)
    if pixel_mm is not None:
        size, sp = list(img.GetSize()), list(spacing)
        new_size = [1 if ax == a else max(2, int(round(size[ax] * sp[ax] / pixel_mm))) for ax in range(3)]
        new_sp = [sp[ax] if ax == a else size[ax] * sp[ax] / new_size[ax] for ax in range(3)]
        # the same field of view: the first pixel's centre moves by half the change of pixel size
        shift = np.array([0.0 if ax == a else (new_sp[ax] - sp[ax]) / 2 for ax in range(3)])
        new_origin = np.asarray(img.GetOrigin()) + np.asarray(g.direction).reshape(3, 3) @ shift
        img = sitk.Resample(img, new_size, sitk.Transform(), sitk.sitkLinear, tuple(float(v) for v in new_origin),
                            tuple(float(v) for v in new_sp), img.GetDirection(), 0.0, sitk.sitkFloat32)
    arr = sitk.GetArrayFromImage(img)
    arr += rng.normal(0.0, noise, arr.shape).astype(np.float32)
    out = sitk.GetImageFromArray(arr)
    out.CopyInformation(img)
    return out


def _truth_from_fields(truth_dir: str, planning_mm: np.ndarray, planning: "Geometry | None" = None) -> dict | None:
    """``{"truth_mm": (frames, N, 3)}`` from a folder of displacement fields (``frame_NNNN.nii.gz``, or a
    ``make-truth`` folder's ``fields/``), each sampled at the planning positions; None when there are none.
    ``planning``: the track's planning grid; fields on another grid (another scan's truth) are refused."""
    import glob

    from ..fields import read_field, sample_field
    from ..images import grid_differences

    folder = os.path.join(truth_dir, "fields") if os.path.isdir(os.path.join(truth_dir, "fields")) else truth_dir
    paths = sorted(glob.glob(os.path.join(folder, "frame_*.nii*")))
    if not paths:
        return None
    out = []
    for p in paths:
        g = Geometry.of(sitk.ReadImage(p))  # the field's own grid: the planning grid it was made on
        diff = grid_differences(g, planning) if planning is not None else []
        if diff:
            raise InputError(f"the truth field {p} is not on the track's planning grid ({'; '.join(diff)}): the truth of "
                             "another scan?")
        out.append(planning_mm + sample_field(read_field(p, g), g, planning_mm))
    return {"truth_mm": np.asarray(out), "planning_mm": planning_mm}


def evaluate_track(track_dir: str, truth_dir: str) -> dict:
    """Per frame and overall: pancreas error (mean, p95, mm), Dice and centroid error of the estimate and of
    ``propagate`` and ``initial``; every organ's mean error, p95 and superior-inferior error (``organs``; ``seen``: whether
    some frame's registration measured it), and for the organs no frame measured the copy with the ``nearest`` and
    ``global`` rules (the baselines with the same information); latency median and p95 (s). ``truth_dir``: a ``make-cine`` truth (``positions.npz``) or displacement fields (a
    ``make-truth`` folder, or a folder of ``frame_NNNN.nii.gz`` on the planning grid)."""
    from .io import read_csv

    if not os.path.isdir(track_dir):
        raise InputError(f"--track {track_dir} is not a folder; give the --out folder of a `warpmpm track`")
    fix = "give the --out folder of a finished `warpmpm track`, or track again"
    rows = read_csv(os.path.join(track_dir, "track.csv"), "track table", ("frame", "latency_s"), fix, torn="refuse")
    if not os.path.exists(os.path.join(track_dir, "particles.npz")):
        raise InputError(f"{os.path.join(track_dir, 'particles.npz')} not found; {fix}")
    try:
        tr = np.load(os.path.join(track_dir, "particles.npz"))
        tr = {k: tr[k] for k in ("planning_mm", "estimate_mm", "propagate_mm", "organ_index", "organs", "nearest_mm", "global_mm",
                                 "measured_organs") if k in tr.files or k not in ("nearest_mm", "global_mm", "measured_organs")}
    except Exception as exc:  # noqa: BLE001 - numpy's many ways to fail on a broken archive
        raise InputError(f"{os.path.join(track_dir, 'particles.npz')} cannot be read ({type(exc).__name__}: {exc}); {fix}") from None
    if os.path.exists(os.path.join(truth_dir, "positions.npz")):
        gt = np.load(os.path.join(truth_dir, "positions.npz"))
    else:
        lab0 = os.path.join(track_dir, "labels", "frame_0000.nii.gz")
        gt = _truth_from_fields(truth_dir, tr["planning_mm"],
                                Geometry.of(sitk.ReadImage(lab0)) if os.path.exists(lab0) else None)
        if gt is None:
            raise InputError(f"{truth_dir} holds neither positions.npz (make-cine) nor displacement fields (frame_NNNN.nii.gz)")
    if tr["planning_mm"].shape != gt["planning_mm"].shape or not np.allclose(tr["planning_mm"], gt["planning_mm"], rtol=0, atol=0.01):
        raise InputError("the track and the truth were built on different particle models (organs or particle step differ)")
    if len(tr["estimate_mm"]) != len(gt["truth_mm"]):
        raise InputError(f"the track holds {len(tr['estimate_mm'])} frames and the truth {len(gt['truth_mm'])}: the truth of "
                         "another series?")
    n = len(gt["truth_mm"])
    pan = tr["organ_index"] == list(tr["organs"]).index("pancreas")
    lab = sitk.ReadImage(os.path.join(track_dir, "labels", "frame_0000.nii.gz"))

    geom = Geometry.of(lab)
    methods = {"estimate": tr["estimate_mm"], "propagate": tr["propagate_mm"], "initial": np.repeat(tr["planning_mm"][None], n, 0)}
    frames = []
    for k in range(n):
        truth = gt["truth_mm"][k][pan]
        rec = {"frame": k, "latency_s": float(rows[k]["latency_s"]) if k < len(rows) else float("nan")}
        for name, arr in methods.items():
            est = arr[k][pan]
            e = np.linalg.norm(est - truth, axis=1)
            rec[name] = {"error_mm": float(e.mean()), "p95_mm": float(np.percentile(e, 95)),
                         "dice": dice(voxelize(est, geom), voxelize(truth, geom)),
                         "centroid_error_mm": float(np.linalg.norm(est.mean(0) - truth.mean(0)))}
        frames.append(rec)
    results = {name: {key: float(np.mean([f[name][key] for f in frames])) for key in ("error_mm", "p95_mm", "dice", "centroid_error_mm")}
               for name in methods}
    organs = list(tr["organs"])
    measured = set(str(o) for o in tr["measured_organs"]) if "measured_organs" in tr else None
    unseen = [o for o in organs if measured is not None and str(o) not in measured]
    for name in ("nearest", "global"):  # the baselines of the organs no frame measured (the copy with those rules)
        if f"{name}_mm" in tr and unseen:
            methods[name] = tr[f"{name}_mm"]
    for name, arr in methods.items():  # every organ, averaged over the frames
        results.setdefault(name, {})["organs"] = {}
        for i, o in enumerate(organs):
            if name in ("nearest", "global") and o not in unseen:
                continue
            sel = tr["organ_index"] == i
            err = np.stack([arr[k][sel] - gt["truth_mm"][k][sel] for k in range(n)])  # (frames, n, 3)
            d = np.linalg.norm(err, axis=2)
            results[name]["organs"][str(o)] = {"error_mm": float(d.mean()), "p95_mm": float(np.mean(np.percentile(d, 95, axis=1))),
                                               "si_mm": float(np.abs(err[..., 2]).mean())}
            if measured is not None:
                results[name]["organs"][str(o)]["seen"] = str(o) in measured
    lat = np.array([f["latency_s"] for f in frames[1:]] or [frames[0]["latency_s"]])
    return {"results": results, "latency_s": {"median": float(np.median(lat)), "p95": float(np.percentile(lat, 95))}, "frames": frames}


def plot_track_errors(evaluation: dict, path: str) -> None:
    """PNG of the pancreas error (mean, with p95 dashed) against frame for the estimate and the baselines of
    an :func:`evaluate_track` result, written under a temporary name and renamed (no half-written file)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = evaluation["frames"]
    if not frames:
        raise InputError("the evaluation holds no frame to plot")
    x = [f["frame"] for f in frames]
    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    for name, colour in (("estimate", "tab:blue"), ("propagate", "tab:orange"), ("initial", "tab:grey")):
        if name not in frames[0]:
            continue
        mean = evaluation["results"][name]["error_mm"]
        ax.plot(x, [f[name]["error_mm"] for f in frames], "-o", ms=3, color=colour, label=f"{name} (mean {mean:.2f} mm)")
        ax.plot(x, [f[name]["p95_mm"] for f in frames], "--", color=colour, alpha=0.5, lw=1)
    ax.set_xlabel("frame")
    ax.set_ylabel("pancreas error (mm); dashed: p95")
    lat = evaluation.get("latency_s", {})
    ax.set_title(f"tracking error per frame (latency median {lat.get('median', float('nan')):.2f} s, "
                 f"p95 {lat.get('p95', float('nan')):.2f} s)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    tmp = path + ".tmp.png"
    try:
        fig.savefig(tmp)
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.remove(tmp)
