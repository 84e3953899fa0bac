"""The README's Python example runs as written (from the repository root)."""

import os
import re

from conftest import ROOT


def test_the_readme_example_runs(capsys):
    text = (ROOT / "README.md").read_text()
    section = text.split("## From Python", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        exec(compile(code, "README.md", "exec"), {})
    finally:
        os.chdir(cwd)
    out = capsys.readouterr().out
    assert "tip sag" in out and "'estimate': 'OutputError'" in out
