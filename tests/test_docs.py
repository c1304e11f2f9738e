"""The documentation holds no path of the machine it was written on: a reader's clone has none of
them (issue 45, point 7: a report's command copied into docs/ named the author's folders)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: Absolute paths under the usual roots of home and work folders (example paths under /tmp are fine).
MACHINE_PATH = re.compile(r"(?<![\w.~-])/(?:work|home|root|Users|mnt|scratch|data)/[\w.-]+")


def test_the_docs_name_no_folder_of_the_machine_they_were_written_on() -> None:
    pages = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    assert len(pages) > 10
    found = [
        f"{page.relative_to(REPO)}:{number}: {match}"
        for page in pages
        for number, line in enumerate(page.read_text().splitlines(), 1)
        for match in [*MACHINE_PATH.findall(line), *([str(REPO)] if str(REPO) in line else [])]
    ]
    assert not found, "\n".join(found)


def test_every_promise_of_the_guarantees_names_tests_that_exist() -> None:
    """docs/reference/guarantees.md lists each promise beside the tests that enforce it (issue 45)."""
    text = (REPO / "docs" / "reference" / "guarantees.md").read_text()
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


#: ``COMMIT:bench/NAME``, as in ``git show 3c45852:bench/profile_update.py``.
REMOVED_SCRIPT = re.compile(r"\b([0-9a-f]{7,40}):bench/([\w.-]+\.(?:py|sh))")


def test_every_cited_bench_script_exists_or_its_citation_says_where_it_went() -> None:
    """bench/ keeps the lasting benchmarks; a one-off study's script is removed once its findings
    are in the docs (issue 44). A page or module that still cites a removed script must say so and
    name a commit that has it (``git show COMMIT:bench/NAME``), so the citation never dangles."""
    pages = [
        REPO / "README.md",
        *sorted((REPO / "docs").rglob("*.md")),
        *sorted((REPO / "mapless").rglob("*.py")),
        *sorted((REPO / "bench").iterdir()),
        *sorted((REPO / "mapless" / "configs").rglob("*.yaml")),
    ]
    dangling, recovered = [], set()
    for page in pages:
        text = page.read_text()
        pointers = {name: commit for commit, name in REMOVED_SCRIPT.findall(text)}
        for name in set(re.findall(r"\bbench/([\w.-]+\.(?:py|sh))\b", text)):
            if (REPO / "bench" / name).is_file():
                continue
            if name in pointers:
                recovered.add((pointers[name], name))
            else:
                dangling.append(f"{page.relative_to(REPO)}: bench/{name}")
    assert not dangling, dangling
    assert recovered  # the removed studies are cited (docs/results/speed.md lists them all)
    if (REPO / ".git").exists() and shutil.which("git"):
        for commit, name in sorted(recovered):
            found = subprocess.run(
                ["git", "-C", str(REPO), "cat-file", "-e", f"{commit}:bench/{name}"], capture_output=True
            )
            assert found.returncode == 0, f"commit {commit} has no bench/{name}"
