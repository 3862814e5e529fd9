"""Materials as data (warpmpm.materials): the built-in tables, a user's JSON table, and what the solvers make of them:
linear elasticity is blind to a uniform scaling of every modulus and sees a change of their ratios."""

import json

import numpy as np
import pytest

from warpmpm.errors import InputError
from warpmpm.experiment.case import prepare_case
from warpmpm.experiment.config import CaseConfig
from warpmpm.materials import TISSUE_NAMES, material_table
from warpmpm.model import PAPER_MATERIALS
from warpmpm.slices import driven_indices
from warpmpm.solvers.completion import CompletionConfig, CompletionModel, complete


def _write(tmp_path, filename, materials, **extra):
    path = tmp_path / filename
    path.write_text(json.dumps({"materials": materials, **extra}))
    return str(path)


def test_the_built_in_tables_say_what_they_are_and_where_from():
    paper, tissue = material_table("paper"), material_table("tissue")
    assert paper.entries["duodenum"] == (PAPER_MATERIALS["duodenum"].mu_pa, PAPER_MATERIALS["duodenum"].lam_pa) == (3.38e6, 8.11e7)
    assert tissue.entries["pancreas"][0] == pytest.approx(1300.0)  # the middle of 1.0-1.6 kPa (MR elastography)
    nu = tissue.to_json()["materials"]["pancreas"]["nu"]
    assert nu == pytest.approx(0.47)  # the middle of 0.45-0.49
    assert paper.entries["liver"] == tissue.entries["liver"]  # the paper names only the four organs
    assert set(paper.entries) == set(tissue.entries) == set(TISSUE_NAMES)
    assert all(paper.sources[t] and tissue.sources[t] for t in TISSUE_NAMES)


def test_a_users_table_is_read_in_pa_and_checked(tmp_path):
    """nu gives lambda = 2 mu nu / (1 - 2 nu); a tissue not named comes from ``tissue`` (and says so); a modulus in kPa,
    an unknown tissue, both lambda and nu, or a file that is not JSON are refused naming the file and the fix."""
    path = _write(tmp_path, "mine.json", {"pancreas": {"mu_pa": 1500, "nu": 0.45, "source": "MRE of this patient"}}, name="mine")
    t = material_table(path)
    assert t.name == "mine" and t.entries["pancreas"] == (1500.0, pytest.approx(2 * 1500 * 0.45 / (1 - 0.9)))
    assert t.sources["pancreas"] == "MRE of this patient" and t.sources["stomach"].startswith("not in ")
    assert t.entries["stomach"] == material_table("tissue").entries["stomach"]
    for bad, match in (({"pancreas": {"mu_pa": 1.2, "nu": 0.45}}, "kPa"), ({"spleen": {"mu_pa": 900, "nu": 0.45}}, "unknown tissue"),
                       ({"pancreas": {"mu_pa": 900, "nu": 0.45, "lam_pa": 1e4}}, "one of lam_pa or nu"),
                       ({"pancreas": {"mu_pa": 900, "nu": 0.5}}, r"\[0, 0.5\)"), ({}, "non-empty")):
        with pytest.raises(InputError, match=match):
            material_table(_write(tmp_path, "bad.json", bad))
    (tmp_path / "text.json").write_text("pancreas 1.2 kPa")
    with pytest.raises(InputError, match="not JSON"):
        material_table(str(tmp_path / "text.json"))
    with pytest.raises(InputError, match="neither a table"):
        material_table("elastography")
    with pytest.raises(InputError):
        CaseConfig(materials=str(tmp_path / "missing.json"))  # refused when the configuration is built, before work


@pytest.fixture(scope="module")
def phantom():
    prep = prepare_case(CaseConfig(phantom_resolution=3.0, device="cpu"))
    return prep, prep.model("psdl")


def _completion(prep, model, materials):
    """The equilibrium given a sheared sagittal plane (the pancreas's): the interior's motion depends on the ratios of
    the tissues' moduli."""
    s = prep.resolve_slices(model, f"sagittal:{int(np.median(model.voxel_ijk[model.organ_slice('pancreas'), 0]))}")
    idx = driven_indices(model, s)
    x = model.positions_mm
    c = x[idx].mean(0)
    shear = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.08], [0.0, 0.05, 0.0]])  # AP by SI and SI by AP: in the plane
    target = x + (x - c) @ shear.T
    P = np.diag([0.0, 1.0, 1.0])
    cm = CompletionModel(prep.case, "amos", model, CompletionConfig(materials=materials, rtol=1e-9, observed_first=False))
    r = complete(cm, idx, target[idx], np.tile(P, (len(idx), 1, 1)), target)
    assert r.converged
    return r.positions_mm, cm


def test_the_completion_takes_the_table_and_only_its_ratios_matter(phantom, tmp_path):
    """Every modulus of ``tissue`` times 10: the same equilibrium (linear elasticity and the observation springs, in
    units of the soft tissue's modulus, scale together); the soft tissue 20 times stiffer than ``tissue``: another one.
    The points of each tissue carry the table's moduli."""
    prep, model = phantom
    base = material_table("tissue")
    ten = _write(tmp_path, "ten.json", {t: {"mu_pa": 10 * mu, "lam_pa": 10 * lam} for t, (mu, lam) in base.entries.items()})
    stiff_mu, stiff_lam = base.entries["soft_tissue"]
    stiff = _write(tmp_path, "stiff.json", {"soft_tissue": {"mu_pa": 20 * stiff_mu, "lam_pa": 20 * stiff_lam}})
    a, cm = _completion(prep, model, "tissue")
    b, cm10 = _completion(prep, model, ten)
    c, _ = _completion(prep, model, stiff)
    assert np.allclose(cm10.point_mu_pa, 10 * cm.point_mu_pa) and np.allclose(cm10.point_lam_pa, 10 * cm.point_lam_pa)
    moved = np.linalg.norm(a - model.positions_mm, axis=1).max()
    assert moved > 1.0
    assert np.abs(b - a).max() < 1e-4 * moved
    assert np.abs(c - a).max() > 0.02 * moved
