"""README's worked example runs as written (from the repository root, as a reader would paste it)."""

import os
import re
import warnings



ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def test_readme_python_blocks_run(monkeypatch, capsys):
    """Without ../shared: the blocks build on the built-in phantom."""
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


def test_readme_commands_are_the_commands_warpmpm_takes():
    """Every `warpmpm ...` line of README's shell blocks parses with the command line it documents (options that exist,
    values they accept); the main job and the set-up script it names exist."""
    import shlex

    from warpmpm.cli import build_parser

    text = open(os.path.join(ROOT, "README.md")).read()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    commands = []
    for block in blocks:
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split("#")[0].strip()
            if line.startswith(("warpmpm ", ".venv/bin/warpmpm ")):
                commands.append(shlex.split(line)[1:])
            elif line.startswith(("bash ", ".venv/bin/python ")) and line.split()[1].endswith((".sh", ".py")):
                assert os.path.exists(os.path.join(ROOT, line.split()[1])), line
    assert len(commands) >= 6
    parser = build_parser()
    for argv in commands:
        parser.parse_args(argv)  # exits (a failed test) on an unknown option or a refused value
