"""The files a project ships at its root: the licence pyproject.toml names, a changelog and a
citation file that cites ermrl and the ER-MRL paper."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


def _project() -> dict[str, Any]:
    """``[project]`` of pyproject.toml (tomllib: Python 3.11 and later)."""
    tomllib = pytest.importorskip("tomllib")
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def test_the_license_is_the_mit_licence_pyproject_names() -> None:
    assert _project()["license"] == {"text": "MIT"}
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert text.startswith("MIT License\n")
    assert "Copyright (c) 2026 the ermrl authors" in text
    assert 'THE SOFTWARE IS PROVIDED "AS IS"' in text


def test_the_changelog_keeps_a_changelog() -> None:
    text = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    assert text.startswith("# Changelog\n")
    assert "keepachangelog.com" in text
    assert re.search(r"^## \[Unreleased\]$", text, flags=re.M)
    assert re.search(r"^### (Added|Changed|Fixed)", text, flags=re.M)


def test_the_citation_file_cites_ermrl_and_the_er_mrl_paper() -> None:
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert cff["cff-version"] == "1.2.0"
    assert "ermrl" in cff["title"] and cff["message"]
    assert cff["authors"] and all("name" in a or "family-names" in a for a in cff["authors"])
    assert str(cff["version"]) == _project()["version"]
    assert cff["license"] == "MIT"
    (paper,) = cff["references"]
    assert paper["title"] == "Evolving Reservoirs for Meta Reinforcement Learning"
    assert [a["family-names"] for a in paper["authors"]] == [
        "Léger",
        "Hamon",
        "Nisioti",
        "Hinaut",
        "Moulin-Frier",
    ]
    assert paper["year"] == 2024
    assert "arXiv:2312.06695" in {i["value"] for i in paper["identifiers"]}
