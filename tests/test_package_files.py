"""Files a newcomer relies on: the licence and the citation agree with pyproject."""

from __future__ import annotations

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


def test_readme_links_resolve_and_keeps_what_a_newcomer_needs():
    """Every local image or file the README points to exists, and its core sections are there."""
    import re

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    targets = re.findall(r"\]\(((?:docs|examples|benchmarks)/[^)#\s]+)\)", text)
    assert targets, "the README shows the figures in docs/"
    missing = [t for t in targets if not (ROOT / t).exists()]
    assert not missing, missing
    headings = set(re.findall(r"^#+ (.+)$", text, flags=re.M))
    for needed in (
        "Quick start",
        "Installing it elsewhere",
        "Reading the results",
        "The HTML report",
        "From a Python console",
        "Commands",
        "Results",
        "License",
        "Citing",
    ):
        assert needed in headings, needed
    assert "make test" in text and "make demo" in text
