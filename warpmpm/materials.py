"""Organ and tissue materials as data: one table per name, every entry in Pa with its source.

A table gives each tissue's shear modulus ``mu_pa`` and first Lame parameter ``lam_pa`` (Pa; Poisson's ratio
``nu = lam / (2 (lam + mu))``) and where the values come from. Two are built in:

- ``paper``: the seed paper's four organ materials (its table "Parameters of simulation":
  :data:`warpmpm.model.PAPER_MATERIALS`; the duodenum's mu 3.38 MPa, the stomach's 168 kPa: far stiffer than
  elastography measures), the other tissues as ``tissue``. What the seed's slice-driven MPM uses by default.
- ``tissue``: every tissue at the middle of its published range (:data:`warpmpm.anatomy.TISSUE_RANGES`: in-vivo MR
  elastography where it exists). What the completion uses by default; the finite-element truths draw from the same
  ranges per case.

A JSON file gives a table of one's own (``--materials FILE``)::

    {"name": "my elastography", "materials": {
        "pancreas": {"mu_pa": 1300, "nu": 0.49, "source": "MRE of this patient, 2026-11-02"},
        "duodenum": {"mu_pa": 1500, "lam_pa": 7.35e4, "source": "..."}}}

each entry with ``mu_pa`` and one of ``lam_pa`` or ``nu``; a tissue it does not name is taken from ``tissue`` (and
the record says so). Which table each estimator uses: :attr:`warpmpm.tracker.TrackerConfig.materials`,
:attr:`warpmpm.experiment.config.CaseConfig.materials` (``None``: each estimator's own default, above). The copy uses
no materials.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

from .errors import InputError

__all__ = ["MaterialTable", "TABLES", "material_table", "TISSUE_NAMES"]

#: the tissues a table may name (the method's organs, and the completion's other tissues)
TISSUE_NAMES = ("pancreas", "stomach", "duodenum", "left_kidney", "liver", "soft_tissue", "bone")


@dataclass(frozen=True)
class MaterialTable:
    """Per tissue ``(mu_pa, lam_pa)`` in Pa, and each entry's source.

    Attributes:
        name: the table's name (``paper``, ``tissue``, or a file's ``name``). entries: tissue -> ``(mu_pa, lam_pa)``.
        sources: tissue -> where its values come from. path: the file it was read from (None: built in).
    """

    name: str
    entries: dict
    sources: dict = field(default_factory=dict)
    path: str | None = None

    def organ_materials(self, organs=("pancreas", "stomach", "duodenum", "left_kidney")) -> dict:
        """``organ -> warpmpm.model.Material`` for the particle model (density: soft tissue's)."""
        from .model import Material

        return {o: Material(lam_pa=self.entries[o][1], mu_pa=self.entries[o][0]) for o in organs if o in self.entries}

    def to_json(self) -> dict:
        """The table as recorded in ``track.json`` and ``run``'s JSON: name, file, and per tissue mu, lambda, nu, source."""
        return {"name": self.name, "path": self.path, "materials": {
            t: {"mu_pa": mu, "lam_pa": lam, "nu": lam / (2.0 * (lam + mu)), "source": self.sources.get(t, "")}
            for t, (mu, lam) in self.entries.items()}}


def _tissue_table() -> MaterialTable:
    from .anatomy import TISSUE_RANGES, nominal_material

    entries = {t: nominal_material(t) for t in TISSUE_NAMES}
    sources = {t: f"middle of the published range: {TISSUE_RANGES[t].source}" for t in TISSUE_NAMES}
    return MaterialTable("tissue", entries, sources)


def _paper_table() -> MaterialTable:
    from .model import PAPER_MATERIALS

    base = _tissue_table()
    entries, sources = dict(base.entries), dict(base.sources)
    for o, m in PAPER_MATERIALS.items():
        entries[o] = (m.mu_pa, m.lam_pa)
        sources[o] = "the seed paper's table 'Parameters of simulation' (warpmpm.model.PAPER_MATERIALS)"
    return MaterialTable("paper", entries, sources)


#: the built-in tables by name
TABLES = {"paper": _paper_table, "tissue": _tissue_table}


def _number(v, what: str, path: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"--materials {path}: {what} must be a finite number, got {v!r}")
    return float(v)


def _read_table(path: str) -> MaterialTable:
    if not os.path.isfile(path):
        raise InputError(f"--materials {path!r} is neither a table ({', '.join(TABLES)}) nor a JSON file")
    try:
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
    except (UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"--materials {path} is not JSON ({exc}); write {{\"materials\": {{\"pancreas\": {{\"mu_pa\": "
                         "1200, \"nu\": 0.49, \"source\": \"...\"}}}}}}") from None
    mats = doc.get("materials") if isinstance(doc, dict) else None
    if not isinstance(mats, dict) or not mats:
        raise InputError(f"--materials {path}: a JSON object with a non-empty \"materials\" object is required")
    base = _tissue_table()
    entries, sources = dict(base.entries), {t: f"not in {path}: {s}" for t, s in base.sources.items()}
    for tissue, e in mats.items():
        if tissue not in TISSUE_NAMES:
            raise InputError(f"--materials {path}: unknown tissue {tissue!r}; use {', '.join(TISSUE_NAMES)}")
        if not isinstance(e, dict) or "mu_pa" not in e or ("lam_pa" in e) == ("nu" in e):
            raise InputError(f"--materials {path}, {tissue}: give mu_pa and one of lam_pa or nu")
        mu = _number(e["mu_pa"], f"{tissue}.mu_pa", path)
        if not 50.0 <= mu <= 1e10:
            raise InputError(f"--materials {path}, {tissue}: mu_pa {mu:g} Pa is outside any tissue's shear modulus (50 Pa .. "
                             "10 GPa; fat is about 300 Pa): is it in kPa? Write it in Pa")
        if "nu" in e:
            nu = _number(e["nu"], f"{tissue}.nu", path)
            if not 0.0 <= nu < 0.5:
                raise InputError(f"--materials {path}, {tissue}: Poisson's ratio {nu:g} must be in [0, 0.5)")
            lam = 2.0 * mu * nu / (1.0 - 2.0 * nu)
        else:
            lam = _number(e["lam_pa"], f"{tissue}.lam_pa", path)
            if lam < 0:
                raise InputError(f"--materials {path}, {tissue}: lam_pa {lam:g} must be >= 0")
        entries[tissue] = (mu, lam)
        sources[tissue] = str(e.get("source", f"{path} (no source given)"))
    return MaterialTable(str(doc.get("name") or os.path.basename(path)), entries, sources, os.path.abspath(path))


def material_table(spec) -> MaterialTable:
    """The table named ``spec`` (:data:`TABLES`), read from the JSON file ``spec``, or ``spec`` itself when it is one;
    :class:`InputError` naming the fix otherwise."""
    if isinstance(spec, MaterialTable):
        return spec
    if not isinstance(spec, str) or not spec:
        raise InputError(f"materials must be {', '.join(TABLES)} or a JSON file, got {spec!r}")
    if spec in TABLES:
        return TABLES[spec]()
    return _read_table(spec)
