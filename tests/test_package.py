"""The package's public surface: every name a module lists in ``__all__`` exists, README's names are importable from
``warpmpm`` without loading Warp kernels first, and no two modules of the package import each other."""

import ast
import importlib
import os
import pkgutil
import subprocess
import sys

import pytest

import warpmpm

ROOT = os.path.dirname(warpmpm.__file__)


def test_every_listed_name_exists():
    for info in pkgutil.walk_packages(warpmpm.__path__, "warpmpm."):
        if ".viewer" in info.name or info.name.endswith(".__main__"):
            continue
        mod = importlib.import_module(info.name)
        for name in getattr(mod, "__all__", []):
            assert hasattr(mod, name), f"{info.name}.__all__ lists {name!r}, which it does not define"


def test_readme_names_from_the_package_without_loading_warp():
    code = ("import sys, warpmpm; assert 'warp' not in sys.modules; "
            "from warpmpm import run_case, CaseConfig, make_truth, write_field, complete, CompletionConfig; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr


def _imports(path: str, package: str) -> set[str]:
    """Modules of the package ``path`` imports at module level, type-checking imports included (function bodies left
    out: a late import inside a function is how a lower layer may call an upper one without a circle)."""
    tree = ast.parse(open(path).read())
    out = set()
    body = list(tree.body)
    for node in tree.body:
        if isinstance(node, ast.If):
            body += node.body
    for node in body:
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
            target = f"{base}.{node.module}" if node.module else base
            out.add(target)
            for a in node.names:
                out.add(f"{target}.{a.name}")
    return out


def test_no_two_modules_import_each_other():
    mods = {}
    for dirpath, _, files in os.walk(ROOT):
        for f in files:
            if f.endswith(".py"):
                rel = os.path.relpath(os.path.join(dirpath, f), os.path.dirname(ROOT))[:-3].replace(os.sep, ".")
                name = rel[: -len(".__init__")] if rel.endswith(".__init__") else rel
                package = name if f == "__init__.py" else name.rsplit(".", 1)[0]
                mods[name] = _imports(os.path.join(dirpath, f), package)
    pairs = [(a, b) for a in mods for b in mods if a < b and b in mods[a] and a in mods[b]
             and not b.startswith(a + ".") and not a.startswith(b + ".")]
    assert not pairs, f"modules importing each other at module level: {pairs}"


def test_the_library_never_imports_the_viewer():
    """viewer/ sits beside the package and only reads; of the package, only the command line imports it, inside the
    commands that write or open recordings (never at module level)."""
    for dirpath, _, files in os.walk(ROOT):
        for f in files:
            if not f.endswith(".py"):
                continue
            path = os.path.join(dirpath, f)
            tree = ast.parse(open(path).read())
            top = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
            names = [a.name for n in top if isinstance(n, ast.Import) for a in n.names] + [
                n.module or "" for n in top if isinstance(n, ast.ImportFrom)]
            assert not any(m == "viewer" or m.startswith("viewer.") for m in names), path
            if not os.path.relpath(path, ROOT).startswith("cli" + os.sep):
                assert "from viewer" not in open(path).read() and "import viewer" not in open(path).read(), path


def test_no_host_module_is_over_about_500_lines():
    """Host code reads in rooms: a module without Warp kernels stays under ~500 lines (kernel modules may be longer)."""
    long = []
    for dirpath, _, files in os.walk(ROOT):
        for f in files:
            if f.endswith(".py"):
                text = open(os.path.join(dirpath, f)).read()
                if "@wp.kernel" not in text and text.count("\n") > 500:
                    long.append((os.path.relpath(os.path.join(dirpath, f), ROOT), text.count("\n")))
    assert not long, f"host modules over 500 lines: {long}"


def test_the_architecture_page_names_modules_that_exist():
    """docs/architecture.md: every module its rooms table and its solvers' room name exists, and every
    `module.name` of a tracked frame's walk is an attribute of that module (issue 53: the page had drifted)."""
    import importlib
    import re

    text = open(os.path.join(ROOT, "..", "docs", "architecture.md")).read()
    rooms, solvers_room = text.split("## The solvers' room")[0], text.split("## The solvers' room")[1].split("## A tracked")[0]
    walk = text.split("## A tracked frame's walk")[1].split("\n## ")[0]
    checked = 0
    for line in rooms.splitlines():
        cells = line.split("|")
        if len(cells) > 3 and "`" in cells[2]:
            for name in re.findall(r"`([a-z_]+/?)`", cells[2]):
                base = os.path.join(ROOT, "..") if name == "viewer/" else ROOT
                assert os.path.exists(os.path.join(base, name.rstrip("/") + ("" if name.endswith("/") else ".py"))), name
                checked += 1
    for line in solvers_room.splitlines():
        cells = line.split("|")
        if len(cells) > 2:
            for name in re.findall(r"`([a-z_]+)`", cells[1]):
                assert os.path.exists(os.path.join(ROOT, "solvers", name + ".py")), name
                checked += 1
    for mod, attr in re.findall(r"`([a-z_]+(?:\.[a-z_]+)*)\.([A-Za-z_]+)`", walk):
        if attr in ("csv", "json", "dcm", "gz", "png", "npz", "rrd"):  # a file name, not a module's attribute
            continue
        for package in ("warpmpm", "warpmpm.solvers"):
            try:
                m = importlib.import_module(f"{package}.{mod}")
            except ImportError:
                continue
            assert hasattr(m, attr), f"{package}.{mod}.{attr}"
            checked += 1
            break
        else:
            raise AssertionError(f"the walk names `{mod}.{attr}`: no such module in warpmpm")
    assert checked > 40


def test_only_what_tracking_needs_is_a_hard_dependency_and_a_missing_extra_names_itself(monkeypatch):
    """Issue 53: pytest, dask, optuna, xgboost and rerun-sdk were hard runtime dependencies. Now extras, and a feature
    that needs a missing one says which `pip install 'warpmpm[...]'` brings it."""
    tomllib = pytest.importorskip("tomllib")
    meta = tomllib.load(open(os.path.join(ROOT, "..", "pyproject.toml"), "rb"))["project"]
    core = " ".join(meta["dependencies"]).lower()
    for pkg in ("pytest", "dask", "optuna", "xgboost", "rerun"):
        assert pkg not in core, pkg
    assert {"models", "sweeps", "viewer", "test"} <= set(meta["optional-dependencies"])
    from warpmpm.errors import InputError, optional
    from warpmpm.plane_placement import PlacementModel

    monkeypatch.setitem(sys.modules, "xgboost", None)  # as if not installed: importing it raises ImportError
    with pytest.raises(InputError, match=r"plan-planes --method model.*pip install 'warpmpm\[models\]'"):
        PlacementModel.load()
    with pytest.raises(InputError, match=r"warpmpm\[viewer\]"):
        optional("rerun.nothing_here", "a Rerun recording (--rrd)")
