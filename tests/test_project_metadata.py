"""What the project says of itself to installers and citers: torch as a range beside the exact CPU pin
of constraints.txt, and a citation file that agrees with the package's version and licence."""

from __future__ import annotations

import tomllib
from pathlib import Path

import yaml
from packaging.requirements import Requirement

import mapless

ROOT = Path(mapless.__file__).resolve().parent.parent


def test_the_citation_file_names_this_version_and_licence_and_cites_the_paper() -> None:
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert citation["version"] == project["version"] == mapless.__version__
    assert citation["license"] == project["license"]
    (paper,) = citation["references"]
    assert paper["title"].startswith("Context vector-based visual mapless navigation")
    assert [a["family-names"] for a in paper["authors"]] == ["Li", "Guo", "Zhang", "Luo"]


def test_torch_is_a_range_that_admits_the_pinned_build_and_other_2x_builds() -> None:
    """Installing mapless into an environment that has another torch 2.x leaves that torch alone; the
    README's exact CPU build stays pinned in constraints.txt."""
    requirements = [
        Requirement(r)
        for r in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    ]
    (torch,) = [r for r in requirements if r.name == "torch"]
    (pin,) = [
        line for line in (ROOT / "constraints.txt").read_text().splitlines() if line.startswith("torch==")
    ]
    assert not any(spec.operator == "==" for spec in torch.specifier)
    assert torch.specifier.contains(pin.removeprefix("torch=="))
    assert torch.specifier.contains("2.6.0") and torch.specifier.contains("2.9.1")
    assert not torch.specifier.contains("2.5.1") and not torch.specifier.contains("3.0.0")
