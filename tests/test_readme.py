"""README's worked example runs as written (from the repository root, as a reader would paste it)."""

import os
import re
import warnings


from conftest import data_case

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def test_readme_python_blocks_run(monkeypatch, capsys):
    data_case("totalseg_mr")  # the first block reads the MR sample
    text = open(os.path.join(ROOT, "README.md")).read()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) >= 3
    monkeypatch.chdir(ROOT)
    scope: dict = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for block in blocks:
            exec(compile(block, "README.md", "exec"), scope)  # noqa: S102 - the README's own code
    assert scope["result"].converged and scope["model"].n > 1000
    assert scope["out"].estimate.error_mm < scope["out"].results["initial"].error_mm
    assert capsys.readouterr().out.strip()  # the last block prints its two errors
