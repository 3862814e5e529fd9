"""``--slices auto``: the driving slice(s) and organ combination the selection models rank best."""

from __future__ import annotations

from dataclasses import replace

from ..errors import InputError
from ..selection import DEFAULT_PLANE_SELECTOR, DEFAULT_SELECTOR, ConditionSelector
from .case import prepare_case
from .config import AUTO_MODES, CaseConfig

__all__ = ["auto_condition"]


def auto_condition(cfg: CaseConfig, selector_path: str | None = None, plane_selector_path: str | None = None) -> tuple[str, str, dict]:
    """(organs, slices) chosen by the selection models for this case, and what they reported.

    ``cfg.slices`` is ``auto`` (or ``auto:a``): the axial slice and organ combination the axial selector
    ranks best. ``auto:ac``, ``auto:as``, ``auto:asc``: organs psdl, the best psdl axial slice, plus
    the first-ranked coronal and/or sagittal slice of the plane selector (the paper's second model).
    The selectors default to the ones shipped with the package (:data:`warpmpm.selection.DEFAULT_SELECTOR`).
    """
    mode = AUTO_MODES.get(cfg.slices or "")
    if mode is None:
        raise InputError(f"unknown --slices {cfg.slices!r}; use one of {', '.join(AUTO_MODES)}")
    sel = ConditionSelector.load(selector_path or DEFAULT_SELECTOR)
    plane = ConditionSelector.load(plane_selector_path or DEFAULT_PLANE_SELECTOR) if mode != "a" else None
    prep = prepare_case(replace(cfg, slices=None, organs="p"))
    ranked, wall = sel.rank(prep.full_model, k=5, combinations=None if mode == "a" else ("psdl",))
    (orientation, k, combo), pred = ranked[0]
    chosen = [prep.label(orientation, k)]
    info = {"selection_ms": wall * 1e3, "predicted": pred, "top": [[list(key), p] for key, p in ranked]}
    for letter, o in (("s", "sagittal"), ("c", "coronal")):
        if letter in mode:
            top, w = plane.rank(prep.full_model, (o,), combinations=("psdl",), k=3)
            chosen.append(prep.label(*top[0][0][:2]))
            info["selection_ms"] += w * 1e3
            info[f"top_{o}"] = [[list(key), p] for key, p in top]
    return combo, ",".join(chosen), info
