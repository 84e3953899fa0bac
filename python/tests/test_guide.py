"""Every Python block of README.md and docs/guide/ runs as written (issue 57).

Each page runs in a folder of its own holding a link to the repository's `assets/`: its RON
blocks are written there as the files their first line names (`// file: NAME.ron`), and its
Python blocks run there in page order in one namespace, as a user pasting them into one
session would. Shell and Rust blocks are run by `xtask/tests/guide.rs` and by the doc tests
of `deform-tests`.
"""

import os
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs/guide").glob("*.md"))


def blocks(text):
    """(info string, first line, text) of each fenced block."""
    out, current = [], None
    for k, line in enumerate(text.splitlines()):
        fence = line.lstrip().startswith("```")
        if current is None and fence:
            current = (line.lstrip()[3:].strip(), k + 2, [])
        elif current is not None and fence:
            out.append((current[0], current[1], "\n".join(current[2]) + "\n"))
            current = None
        elif current is not None:
            current[2].append(line)
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_python_block_runs(page, tmp_path, capsys):
    os.symlink(ROOT / "assets", tmp_path / "assets")
    here = os.getcwd()
    os.chdir(tmp_path)
    try:
        namespace = {"__name__": "__guide__"}
        ran = []
        for info, line, text in blocks(page.read_text()):
            lang = (info.split() or [""])[0]
            if lang == "ron":
                name = text.splitlines()[0].removeprefix("// file: ").strip()
                (tmp_path / name).write_text(text)
            elif lang == "python":
                where = f"{page.relative_to(ROOT)}:{line}"
                exec(compile(text, where, "exec"), namespace)
                ran.append(where)
    finally:
        os.chdir(here)
    with capsys.disabled():
        for where in ran:
            print(f"ran {where}")
