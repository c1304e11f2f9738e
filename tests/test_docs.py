"""What the repository says to its readers: no path of the machine a page was written on, no word
about how the project was made, numbers tied to pages that name their commit, links that resolve."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


#: Absolute paths under the roots of machines' home, work, temporary and install folders (a
#: rendered command once named its ``--reports`` folder under the temp root).
MACHINE_PATH = re.compile(r"(?<![\w.~/-])/(?:tmp|work|home|root|Users|mnt|opt|scratch|data)/[\w.-]*")
#: Words about how the project was made rather than what it is: the numbered working sittings it
#: was written in, who wrote a file, a tracker entry given as the source of a claim.
PROCESS_WORD = re.compile(r"(?i)\b(?:sessions?|sittings?|written\s+by|issues?\s+#?\d+)\b")
#: Text files a reader of the repository meets: the README, the docs, the experiment configs and
#: the package data.
TEXT_SUFFIXES = {".md", ".txt", ".json", ".yaml", ".yml"}


#: The code a reader meets: the package's modules, the benchmarks and the data-building tools.
CODE_SUFFIXES = {".py", ".sh"}


def reader_files(root: Path = REPO) -> list[Path]:
    """The README, every page under docs/ and tests/, every experiment config, every text file of the
    package data, and the code of the package, bench/ and tools/, under ``root``."""
    files = [
        root / "README.md",
        *sorted((root / "docs").rglob("*.md")),
        *sorted((root / "tests").rglob("*.md")),
    ]
    for folder in (root / "experiments", root / "mapless" / "configs", root / "mapless" / "data"):
        files += sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix in TEXT_SUFFIXES)
    for folder in (root / "mapless", root / "bench", root / "tools"):
        files += sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix in CODE_SUFFIXES)
    return [p for p in files if p.is_file()]


def findings(files: list[Path], root: Path = REPO) -> list[str]:
    """``path:line: match`` for every machine path or process word in ``files``."""
    found = []
    for path in files:
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            hits = [*MACHINE_PATH.findall(line), *PROCESS_WORD.findall(line)]
            hits += [str(REPO)] if str(REPO) in line else []
            found += [f"{path.relative_to(root)}:{number}: {hit}" for hit in hits]
    return found


def test_the_scan_finds_each_kind_of_word_and_path(tmp_path: Path) -> None:
    (tmp_path / "docs" / "results").mkdir(parents=True)
    (tmp_path / "mapless" / "data" / "priors").mkdir(parents=True)
    (tmp_path / "README.md").write_text("See the twenty-first session.\nPlain text.\n")
    (tmp_path / "docs" / "results" / "a.md").write_text(
        "Command: `mapless reproduce table1 --reports /tmp/lanes/r`.\nAs issue 42 found.\n"
    )
    (tmp_path / "mapless" / "data" / "priors" / "x.json").write_text(
        '{"source": "a copy, written by a helper"}'
    )
    # A binary file is not a page a reader meets (the path is built: tests name no folder outside).
    (tmp_path / "mapless" / "data" / "x.bin").write_text("/".join(["", "home", "someone"]))
    (tmp_path / "docs" / "b.md").write_text("python at /opt/torch/bin/python3; runs under /Users/me/x\n")
    (tmp_path / "mapless" / "train").mkdir()
    (tmp_path / "mapless" / "train" / "config.py").write_text(
        '"""Settings."""\n\n#: The layout before issue 44.\nA = 1\n'
    )
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "gpu.sh").write_text("# The GPU check (Issue #23).\necho ok\n")
    (tmp_path / "bench" / "x.py").write_text("# A sitting of its own\n")
    hits = findings(reader_files(tmp_path), tmp_path)
    assert [h.split(": ", 1)[0] for h in hits] == [
        "README.md:1",
        "docs/b.md:1",
        "docs/b.md:1",
        "docs/results/a.md:1",
        "docs/results/a.md:2",
        "mapless/data/priors/x.json:1",
        "mapless/train/config.py:3",
        "bench/gpu.sh:1",
        "bench/x.py:1",
    ]
    # Relative folders, a folder under the project and a URL's path are nobody's machine.
    ok = tmp_path / "ok.md"
    ok.write_text(
        "--reports reports/r, ./tmp/x, runs/tmp/y, https://example.org/home/x, issues and sessions of torch\n"
    )
    assert findings([ok], tmp_path) == ["ok.md:1: sessions"]


def test_the_repository_speaks_of_itself_only() -> None:
    """No page, config, data file or module names a folder of the machine it was written on, the
    sittings the project was made in, the author of a copy, or a tracker entry as a source: a reader
    has the versions, the commits and docs/changelog.md."""
    files = reader_files()
    assert len(files) > 40
    assert REPO / "mapless" / "train" / "config.py" in files and REPO / "bench" / "gpu_learning.sh" in files
    found = findings(files)
    assert not found, "\n".join(found)


#: A config the pages name: a shipped file by its path, or a training config by the name
#: ``mapless train`` takes (a path after ``mapless train`` is the reader's own file; a capitalised
#: word, NAME or CONFIG, is a placeholder).
CONFIG_PATH = re.compile(r"mapless/configs/([a-z0-9_/*]+\.yaml)")
TRAIN_NAME = re.compile(r"mapless train ([a-z]\w*)(?=[\s`]|$)", re.M)
#: The configs' folder before they became package data.
OLD_CONFIG_PATH = re.compile(
    r"(?<![\w/.])experiments/(?:budgets|recipes|train_|\w+_(?:smoke|small|medium|long|full)\b|\*)"
)


def missing_configs(pages: list[Path], root: Path = REPO) -> list[str]:
    """``page: reference`` for each config a page names that is not shipped, and each reference to
    the configs' old folder."""
    shipped = root / "mapless" / "configs"
    missing = []
    for page in pages:
        text = page.read_text()
        named = [p for p in CONFIG_PATH.findall(text) if not list(shipped.glob(p))]
        named += [f"{n}.yaml" for n in TRAIN_NAME.findall(text) if not (shipped / f"{n}.yaml").is_file()]
        named += OLD_CONFIG_PATH.findall(text)
        missing += [f"{page.relative_to(root)}: {n}" for n in named]
    return missing


def test_every_config_the_pages_name_is_shipped() -> None:
    pages = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    assert not missing_configs(pages)


def test_a_config_that_is_not_shipped_is_found(tmp_path: Path) -> None:
    (tmp_path / "mapless" / "configs" / "budgets").mkdir(parents=True)
    (tmp_path / "mapless" / "configs" / "train_ppo.yaml").write_text("model: {name: mlp}\n")
    (tmp_path / "mapless" / "configs" / "budgets" / "small.yaml").write_text("seeds: [1]\n")
    page = tmp_path / "a.md"
    page.write_text(
        "mapless train train_ppo --set x=1; `mapless/configs/budgets/small.yaml`, mapless/configs/*.yaml\n"
        "mapless train ./mine.yaml and mapless train --resume RUN, runs/experiments/small/x\n"
    )
    assert missing_configs([page], tmp_path) == []
    page.write_text(
        "mapless train train_gone\nmapless/configs/table1_small.yaml\nsee experiments/budgets/small.yaml\n"
    )
    assert missing_configs([page], tmp_path) == [
        "a.md: table1_small.yaml",
        "a.md: train_gone.yaml",
        "a.md: experiments/budgets",
    ]


#: A calendar date. The guide and the reference say how and why, never when: results and history
#: carry their dates in docs/results/ (with their commits) and docs/changelog.md.
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
#: A Markdown link's target: a results section's anchor may hold its date, the link's text may not.
LINK_TARGET = re.compile(r"\]\([^)\s]*\)")


def dated_lines(pages: list[Path], root: Path = REPO) -> list[str]:
    """``path:line: date`` for every date in ``pages`` outside a link's target."""
    found = []
    for page in pages:
        for number, line in enumerate(page.read_text().splitlines(), 1):
            found += [
                f"{page.relative_to(root)}:{number}: {d}" for d in DATE.findall(LINK_TARGET.sub("]", line))
            ]
    return found


def test_the_guides_and_the_reference_carry_no_dates() -> None:
    pages = sorted((REPO / "docs" / "guide").glob("*.md")) + sorted(
        (REPO / "docs" / "reference").glob("*.md")
    )
    assert len(pages) > 8
    found = dated_lines(pages)
    assert not found, "\n".join(found)


def test_a_date_in_a_guide_is_found_and_an_anchor_is_not(tmp_path: Path) -> None:
    page = tmp_path / "training.md"
    page.write_text(
        "Measured on 2026-12-03: 411.7 frames/s.\n"
        "See [the runs](../results/learning.md#2026-12-04-the-mlp-sanity-model) and seed 2026 of 12-03.\n"
        "Since 2026-12-07 the default is hoz22 ([changelog](../changelog.md)).\n"
    )
    assert dated_lines([page], tmp_path) == ["training.md:1: 2026-12-03", "training.md:3: 2026-12-07"]


def test_every_promise_of_the_guarantees_names_tests_that_exist() -> None:
    """docs/reference/guarantees.md lists each promise beside the tests that enforce it."""
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
    are in the docs. A page or module that still cites a removed script must say so and
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


def test_the_reference_pages_match_the_code_they_are_generated_from() -> None:
    """docs/reference/cli.md and config.md are renderings of the parsers and of TrainConfig: a flag,
    help text or default changed without regenerating them fails here."""
    from mapless.cli.docs import PAGES

    for name, render in PAGES.items():
        page = REPO / "docs" / "reference" / f"{name}.md"
        assert page.read_text() == render(), (
            f"regenerate: python -m mapless.cli.docs {name} > {page.relative_to(REPO)}"
        )


def _code_map():
    """tools/code_map.py, which renders the counted part of docs/reference/architecture.md."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("code_map", REPO / "tools" / "code_map.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_code_map_matches_the_source() -> None:
    """The architecture page's counts (files and lines per unit, what each imports, the files of one
    PPO update of a3c and of cvmeta) are the script's rendering of the source, not typed."""
    code_map = _code_map()
    page = (REPO / "docs" / "reference" / "architecture.md").read_text()
    block = code_map.render()
    assert block in page, "regenerate: python tools/code_map.py --write"
    units = {row[0]: row for row in code_map.module_map()}
    # Hand-checked facts of the source: train/ppo.py is one file of train/, which imports agent/ at
    # module level; __main__.py imports cli/ alone.
    assert units["__main__.py"][1:3] == (1, code_map.line_count(REPO / "mapless" / "__main__.py"))
    assert units["__main__.py"][3] == {"cli/": True}
    assert units["train/"][3]["agent/"] is True
    assert units["train/"][1] == len(list((REPO / "mapless" / "train").glob("*.py")))
    order = list(units)
    assert order.index("scenes/") < order.index("sim/") < order.index("agent/") < order.index("train/")
    a3c, cvmeta = (set(code_map.trace_update(m)) for m in ("a3c", "cvmeta"))
    package = REPO / "mapless"
    assert {
        package / "train" / "ppo.py",
        package / "models" / "base.py",
    } <= a3c
    # The inner loop and φ are the adaptive models' (an update that took no inner step would miss φ).
    assert {
        package / "agent" / "meta.py",
        package / "agent" / "fast_weights.py",
        package / "models" / "learned_loss.py",
    } <= cvmeta - a3c
    assert package / "models" / "a3c.py" in a3c - cvmeta


def test_the_code_map_block_is_replaced_between_its_markers(tmp_path: Path) -> None:
    code_map = _code_map()
    page = f"# Code map\n\nProse.\n\n{code_map.BEGIN}\nold table\n{code_map.END}\n\n## After\n"
    new = code_map.replace_block(page, f"{code_map.BEGIN}\nnew table\n{code_map.END}\n")
    assert new == f"# Code map\n\nProse.\n\n{code_map.BEGIN}\nnew table\n{code_map.END}\n\n## After\n"
    try:
        code_map.replace_block("# Code map without markers\n", "x")
    except SystemExit as refused:
        assert "markers" in str(refused)
    else:
        raise AssertionError("a page without markers was written")
    file = tmp_path / "m.py"
    file.write_text(
        "from typing import TYPE_CHECKING\nfrom mapless.errors import X\n"
        "if TYPE_CHECKING:\n    from mapless.sim.env import NavEnv\n"
        "def f():\n    import mapless.train.ppo\n    from mapless import config\n"
    )
    assert code_map.imports_of(file) == {
        "errors.py": True,
        "sim/": True,
        "train/": False,
        "config.py": False,
    }


def test_the_cli_page_has_a_section_per_command_with_its_flags() -> None:
    from mapless.cli.docs import render_cli

    page = render_cli()
    for command in (
        "## `mapless train`",
        "## `mapless reproduce`",
        "## `mapless scenes build`",
        "## `mapless eval`",
    ):
        assert command in page
    assert "--budget" in page.split("## `mapless reproduce`")[1].split("\n## ")[0]


#: The README's results table lies between these markers, so it can be replaced by a new rendering.
RESULTS_BLOCK = re.compile(r"<!-- results:table1 begin -->(.*?)<!-- results:table1 end -->", re.S)
NUMBER = re.compile(r"[−+-]?\d+\.\d+")
COMMIT = re.compile(r"\bcommit `?[0-9a-f]{7,40}\b")


def results_sections(root: Path = REPO) -> list[str]:
    """Each section (from a heading to the next of the same or a higher level) of docs/results/,
    with the text of its subsections."""
    sections = []
    for page in sorted((root / "docs" / "results").glob("*.md")):
        lines = page.read_text().splitlines()
        heads = [
            (i, len(line) - len(line.lstrip("#")))
            for i, line in enumerate(lines)
            if re.match(r"#{2,4} ", line)
        ]
        for n, (start, level) in enumerate(heads):
            end = next((i for i, lv in heads[n + 1 :] if lv <= level), len(lines))
            sections.append("\n".join(lines[start:end]))
    return sections


def untied_numbers(readme: str, sections: list[str]) -> list[str]:
    """The numbers of the README's results table that no single results section with a commit holds
    all together (empty when one does)."""
    block = RESULTS_BLOCK.search(readme)
    assert block, "the README's results table is not between its markers"
    rows = [
        line for line in block.group(1).splitlines() if line.startswith("|") and not line.startswith("|--")
    ]
    numbers = [n.replace("−", "-").lstrip("+") for row in rows[1:] for n in NUMBER.findall(row)]
    assert numbers
    best: list[str] = numbers
    for section in (s for s in sections if COMMIT.search(s)):
        present = {n.replace("−", "-").lstrip("+") for n in NUMBER.findall(section)}
        missing = [n for n in numbers if n not in present]
        best = min(best, missing, key=len)
    return best


def test_every_number_of_the_readme_table_is_in_a_results_section_with_a_commit() -> None:
    assert not untied_numbers((REPO / "README.md").read_text(), results_sections())


def test_a_readme_number_without_a_committed_section_is_found(tmp_path: Path) -> None:
    (tmp_path / "docs" / "results").mkdir(parents=True)
    readme = "<!-- results:table1 begin -->\n| model | SR |\n|---|---|\n| a3c | 46.8 [43.5, 49.8] |\n<!-- results:table1 end -->"
    page = tmp_path / "docs" / "results" / "t.md"
    page.write_text("## Tied\n\n| a3c | 46.8 [43.5, 49.8] |\n\nMade by mapless 0.1.0, commit 4eaaccb508f2.\n")
    assert untied_numbers(readme, results_sections(tmp_path)) == []
    page.write_text("## No commit\n\n| a3c | 46.8 [43.5, 49.8] |\n\n## Another\n\ncommit 4eaaccb, 46.8\n")
    assert untied_numbers(readme, results_sections(tmp_path)) == ["43.5", "49.8"]
