"""Files a newcomer relies on: the licence and the citation agree with pyproject."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

import itk_nrreval

ROOT = Path(__file__).resolve().parents[1]
tomllib = pytest.importorskip("tomllib")  # Python >= 3.11


def pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_citation_matches_the_package_and_cites_the_paper():
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    project = pyproject()["project"]
    assert cff["cff-version"] == "1.2.0"
    assert cff["version"] == project["version"] == itk_nrreval.__version__
    assert cff["license"] == project["license"]["text"]
    paper = cff["preferred-citation"]
    assert paper["title"] == "Evaluating Registration Without Ground Truth"
    assert [a["family-names"] for a in paper["authors"]][0] == "Twining"
    assert any("2002.10534" in i["value"] for i in paper["identifiers"])


def test_licence_file_matches_pyproject():
    assert pyproject()["project"]["license"]["text"] == "Apache-2.0"
    assert "Apache License" in (ROOT / "LICENSE").read_text()
    assert "Version 2.0" in (ROOT / "LICENSE").read_text()


def _without_code(text: str) -> str:
    """Markdown text without its fenced code blocks, where a link or a heading is not one."""
    return re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)


def _local_links(md: Path) -> list[str]:
    """Targets of the links and images in ``md`` that point into this repository."""
    targets = re.findall(r"\]\(([^)\s]+)\)", _without_code(md.read_text(encoding="utf-8")))
    return [t for t in targets if not re.match(r"[a-z][a-z0-9+.-]*:", t)]


def _heading_anchors(md: Path) -> set[str]:
    """GitHub's anchors for the headings of ``md``: lower case, punctuation dropped, - for space."""
    headings = re.findall(r"^#+ (.+)$", _without_code(md.read_text(encoding="utf-8")), flags=re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings}


def _section(text: str, heading: str) -> str:
    """The text under the level-2 ``heading`` of a markdown page, up to the next level-2 heading."""
    match = re.search(rf"^## {re.escape(heading)}\n(.*?)(?=^## |\Z)", text, flags=re.M | re.S)
    assert match, heading
    return match.group(1)


def test_readme_links_resolve_and_keeps_what_a_newcomer_needs():
    """The README stays a user's guide with its core sections; results live in docs/ pages,
    every one linked from the README, and every local link (README and docs/) resolves."""
    readme = ROOT / "README.md"
    text = readme.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 330, "the README is a user's guide: move results to docs/"
    headings = set(re.findall(r"^#+ (.+)$", _without_code(text), flags=re.M))
    for needed in (
        "Quick start",
        "Installing it elsewhere",
        "Evaluating your own registrations",
        "Reading the results",
        "The HTML report",
        "From a Python console",
        "The Python API",
        "Commands",
        "Large cohorts",
        "Results",
        "Development",
        "License",
        "Citing",
    ):
        assert needed in headings, needed
    # .ci/run runs "the README's test command"
    assert re.search(r"^```\nmake demo\nmake test\n```$", text, flags=re.M)
    assert re.search(r"!\[[^]]*\]\(docs/[\w-]+\.png\)", _section(text, "Results")), (
        "one results figure"
    )

    pages = sorted((ROOT / "docs").glob("*.md"))
    readme_links = {(ROOT / t.split("#")[0]).resolve() for t in _local_links(readme)}
    assert not [p.name for p in pages if p.resolve() not in readme_links]
    results_links = set(re.findall(r"\]\(docs/([\w-]+\.md)\)", _section(text, "Results")))
    for page in (
        "results.md",
        "verdict.md",
        "subject-qc.md",
        "speed.md",
        "large-cohorts.md",
        "generated-data.md",
        "method.md",
    ):
        assert page in results_links, page

    broken = []
    for md in [readme, *pages]:
        for target in _local_links(md):
            path, _, anchor = target.partition("#")
            resolved = (md.parent / path).resolve() if path else md
            if not resolved.exists():
                broken.append(f"{md.name}: {target}")
            elif anchor and resolved.suffix == ".md" and anchor not in _heading_anchors(resolved):
                broken.append(f"{md.name}: {target} (no such heading)")
    assert not broken, broken


def test_the_readmes_python_snippets_run_as_written(tmp_path, monkeypatch):
    """Issue 44: the README's snippets used names they never defined, and one line built a
    stray tuple. Run each block, in order, in one namespace, on the population their first
    comment names, as a reader who pastes them would."""
    import ast

    from itk_nrreval.cli import main

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) >= 2
    monkeypatch.chdir(tmp_path)
    assert main(["synth", "--n", "6", "--spacing", "4", "--out", "population"]) == 0
    namespace: dict = {}
    for block in blocks:
        for statement in ast.parse(block).body:  # a bare tuple is a line that does nothing
            assert not (
                isinstance(statement, ast.Expr) and isinstance(statement.value, ast.Tuple)
            ), ast.get_source_segment(block, statement)
        exec(compile(block, "README.md", "exec"), namespace)
    assert (tmp_path / "results" / "results.json").is_file()
