"""The benchmarks folder as README and docs/performance.md describe it: every script kept in ``benchmarks/`` (and every
study in ``benchmarks/studies/``) keeps its raw numbers in ``results/<script>.json`` beside it, every results file
belongs to a script or is named in the page that quotes it, and no script edits ``sys.path``."""

import ast
import json
import os

import pytest

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
FOLDERS = [os.path.join(ROOT, "benchmarks"), os.path.join(ROOT, "benchmarks", "studies")]


def scripts(folder):
    return sorted(f[:-3] for f in os.listdir(folder) if f.endswith(".py"))


def saves(path):
    """The ``raw.save`` calls of a script whose first argument is ``__file__``, and those whose first is anything else."""
    tree = ast.parse(open(path).read())
    good, bad = 0, 0
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "save" \
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "raw":
            if node.args and isinstance(node.args[0], ast.Name) and node.args[0].id == "__file__":
                good += 1
            else:
                bad += 1
    return good, bad


@pytest.mark.parametrize("folder", FOLDERS, ids=["benchmarks", "studies"])
def test_every_script_keeps_its_numbers_in_results_named_after_it(folder):
    for name in scripts(folder):
        good, bad = saves(os.path.join(folder, f"{name}.py"))
        assert good >= 1 and bad == 0, f"{name}.py: raw.save(__file__, ...) {good} times, otherwise {bad} times"


@pytest.mark.parametrize("folder", FOLDERS, ids=["benchmarks", "studies"])
def test_every_results_json_belongs_to_a_script_and_names_its_machine(folder):
    """A results JSON is a script's (or, its script gone, named on the studies page) and every run in it names its
    machine."""
    names = set(scripts(folder))
    results = os.path.join(folder, "results")
    studies_page = open(os.path.join(ROOT, "benchmarks", "studies", "README.md")).read()
    for f in sorted(os.listdir(results)):
        if not f.endswith(".json"):
            continue
        assert f[:-5] in names or f"results/{f}" in studies_page, \
            f"{os.path.relpath(os.path.join(results, f), ROOT)} has no script {f[:-5]}.py and is not on the studies page"
        with open(os.path.join(results, f)) as fh:
            doc = json.load(fh)
        assert doc["runs"], f
        for run, entry in doc["runs"].items():
            assert entry["machine"] and "data" in entry, (f, run)


def test_every_other_results_file_is_quoted_where_it_is_explained():
    """A plot, a log or a JSON-lines file in a results folder has no script to name it: the page that explains it
    (docs/performance.md or benchmarks/studies/README.md) names it."""
    pages = "".join(open(os.path.join(ROOT, p)).read() for p in ("docs/performance.md", "benchmarks/studies/README.md"))
    for folder in FOLDERS:
        results = os.path.join(folder, "results")
        for f in sorted(os.listdir(results)):
            if not f.endswith(".json"):
                assert f in pages, f"{f} in {os.path.relpath(results, ROOT)} is quoted by neither page"


def test_no_script_edits_sys_path():
    tops = ("benchmarks", "examples", "warpmpm", "viewer", "tests", "scripts")
    for top in tops:
        for dirpath, _, files in os.walk(os.path.join(ROOT, top)):
            for f in files:
                if f.endswith(".py") and f != os.path.basename(__file__):
                    text = open(os.path.join(dirpath, f)).read()
                    assert "sys.path.insert" not in text and "sys.path.append" not in text, os.path.join(dirpath, f)


@pytest.mark.parametrize("folder", FOLDERS, ids=["benchmarks", "studies"])
def test_every_script_answers_help_without_running(folder):
    """``python benchmarks/<script>.py --help`` prints its options and stops (a script without a parser ran whole)."""
    for name in scripts(folder):
        tree = ast.parse(open(os.path.join(folder, f"{name}.py")).read())
        parsers = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "attr", getattr(n.func, "id", "")) == "ArgumentParser"]
        assert parsers, f"{name}.py builds no argparse.ArgumentParser"
