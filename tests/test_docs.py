"""The documentation holds no path of the machine it was written on: a reader's clone has none of
them (issue 45, point 7: a report's command copied into docs/ named the author's folders)."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: Absolute paths under the usual roots of home and work folders (example paths under /tmp are fine).
MACHINE_PATH = re.compile(r"(?<![\w.~-])/(?:work|home|root|Users|mnt|scratch|data)/[\w.-]+")


def test_the_docs_name_no_folder_of_the_machine_they_were_written_on() -> None:
    pages = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    assert len(pages) > 10
    found = [
        f"{page.relative_to(REPO)}:{number}: {match}"
        for page in pages
        for number, line in enumerate(page.read_text().splitlines(), 1)
        for match in [*MACHINE_PATH.findall(line), *([str(REPO)] if str(REPO) in line else [])]
    ]
    assert not found, "\n".join(found)


def test_every_promise_of_the_guarantees_names_tests_that_exist() -> None:
    """docs/guarantees.md lists each promise beside the tests that enforce it (issue 45)."""
    text = (REPO / "docs" / "guarantees.md").read_text()
    promises = re.findall(r"(?ms)^- .*?(?=^- |^\n|^## |\Z)", text)
    assert len(promises) > 30
    untested = [p.splitlines()[0] for p in promises if "tests/" not in p]
    assert not untested, untested
    named = re.findall(r"tests/(test_\w+\.py)::(test_\w+)", text)
    missing = [
        f"{file}::{test}"
        for file, test in named
        if not re.search(rf"^def {test}\(", (REPO / "tests" / file).read_text(), re.MULTILINE)
    ]
    assert not missing, missing
