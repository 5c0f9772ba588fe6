"""Every Python snippet in the README runs as written (each in a fresh interpreter, from the repository
root), and every path the README links to exists."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"


def _snippets() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_the_readme_has_python_snippets():
    assert _snippets(), "the README's Python API section has no ```python block"


@pytest.mark.parametrize("index", range(len(_snippets())))
def test_readme_python_snippet_runs(index, tmp_path):
    code = _snippets()[index]
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, (
        f"README snippet {index} failed:\n{code}\n--- stderr ---\n{run.stderr[-3000:]}"
    )


def test_links_in_the_readme_and_docs_exist():
    missing = []
    for md in [README, *sorted((ROOT / "docs").rglob("*.md"))]:
        for link in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", md.read_text()):
            if not link.startswith(("http://", "https://")) and not (md.parent / link).exists():
                missing.append(f"{md.relative_to(ROOT)} -> {link}")
    assert not missing, f"links to files that do not exist: {missing}"


def test_design_anchors_cited_by_the_code_exist():
    design = (ROOT / "docs" / "design.md").read_text()
    anchors = set(re.findall(r'<a id="([^"]+)"', design))
    cited = set()
    for path in [*(ROOT / "boxjax").rglob("*.py"), *(ROOT / "tests").rglob("*.py")]:
        cited |= set(re.findall(r"docs/design\.md#([a-z0-9-]+)", path.read_text()))
    assert cited and not cited - anchors, f"docs/design.md has no anchor {sorted(cited - anchors)}"


def test_readme_is_short():
    assert len(README.read_text().splitlines()) <= 320
