"""The documentation stays true to the tree: the command-line page is current, every relative link
resolves, the README and model cards keep their length, and no work-log path or dated experiment title
leaks into the product text."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tesseract4d.testing.project_scripts import load_script

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
MODEL_CARDS = sorted((ROOT / "tesseract4d" / "checkpoints").glob("*/MODEL_CARD.md"))
RESEARCH = ROOT / "docs" / "research"
# A folder of one numbered working session, e.g. the runs or outputs folder of session 12.
WORK_LOG_PATH = re.compile(r"\b(?:runs|outputs)/s[0-9]+")
SKIPPED_DIRS = {".git", ".venv", ".deps", "node_modules", "__pycache__"}


def project_files(*suffixes: str) -> list[Path]:
    """The repository's own files with these suffixes (no virtualenv, no git internals)."""
    found = []
    for path in ROOT.rglob("*"):
        rel = path.relative_to(ROOT)
        if path.suffix in suffixes and path.is_file() and not any(
                part in SKIPPED_DIRS or part.startswith(".") for part in rel.parts):
            found.append(path)
    return sorted(found)


def markdown_pages() -> list[Path]:
    """The Markdown a reader follows links through: README, changelog, docs/ and the model cards."""
    pages = [README, ROOT / "CHANGELOG.md", *MODEL_CARDS]
    pages += sorted((ROOT / "docs").rglob("*.md"))
    return [p for p in pages if p.is_file()]


def without_code(text: str) -> str:
    """Markdown text with fenced code blocks and inline code removed (links there are not links)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = heading.strip().lower().replace("`", "")
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def headings(page: Path) -> list[str]:
    return [line.lstrip("#").strip() for line in without_code(page.read_text()).splitlines()
            if re.match(r"^#{1,6} ", line)]


def test_cli_page_is_generated_from_todays_help():
    cli_docs = load_script("cli_docs")
    current = cli_docs.CLI_MD.read_text() if cli_docs.CLI_MD.is_file() else ""
    assert current == cli_docs.render(), "docs/cli.md is stale: run `.venv/bin/python scripts/cli_docs.py`"


def test_cli_page_lists_every_subcommand_of_the_top_level_help():
    cli_docs = load_script("cli_docs")
    names = cli_docs.listed_subcommands(cli_docs.help_text([]))
    assert {"datagen", "train", "predict", "demo"} <= set(names)
    page = cli_docs.render()
    for name in names:
        assert f"## tesseract4d {name}\n" in page


def test_readme_fits_in_250_lines():
    lines = README.read_text().count("\n")
    assert lines <= 250, f"README.md has {lines} lines; move detail into docs/"


def test_each_model_card_fits_in_200_lines():
    assert len(MODEL_CARDS) >= 2, MODEL_CARDS
    for card in MODEL_CARDS:
        lines = card.read_text().count("\n")
        assert lines <= 200, f"{card.relative_to(ROOT)} has {lines} lines"


def test_model_cards_follow_one_template():
    sections = ["Model details", "Inputs and outputs", "Training data", "Training recipe", "Held-out evaluation",
                "Speed per CPU kind", "Limitations", "How to reproduce", "Citation"]
    for card in MODEL_CARDS:
        found = [h for h in headings(card) if h in sections]
        assert found == sections, f"{card.relative_to(ROOT)}: sections {found}"


def test_no_work_log_path_outside_docs_research():
    offenders = []
    for path in project_files(".py", ".md"):
        if RESEARCH in path.parents:
            continue
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if WORK_LOG_PATH.search(line):
                offenders.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    assert not offenders, "folders no reader has:\n" + "\n".join(offenders)


def test_no_work_log_path_in_docs_research_either():
    """The research notes cite commits, which every clone has, not run folders, which no clone has."""
    offenders = [str(p.relative_to(ROOT)) for p in RESEARCH.rglob("*.md") if WORK_LOG_PATH.search(p.read_text())]
    assert not offenders, offenders


def test_no_session_numbers_or_dated_titles_in_product_text():
    pages = [README, *MODEL_CARDS, ROOT / "docs" / "cli.md"]
    for page in pages:
        text = page.read_text()
        assert not re.search(r"\bsessions? [0-9]+", text, flags=re.I), f"{page.relative_to(ROOT)} names a session"
        for heading in headings(page):
            assert not re.search(r"\b20[0-9]{2}-[0-9]{2}-[0-9]{2}\b", heading), f"{page.relative_to(ROOT)}: {heading}"


@pytest.mark.parametrize("page", markdown_pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", without_code(page.read_text())):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path_part, _, anchor = target.partition("#")
        resolved = (page.parent / path_part).resolve() if path_part else page
        if not resolved.exists():
            broken.append(f"{target} (no {resolved})")
        elif anchor and resolved.suffix == ".md" and anchor not in {slug(h) for h in headings(resolved)}:
            broken.append(f"{target} (no heading #{anchor})")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


def test_code_cites_documents_and_headings_that_exist():
    """A comment, docstring or message that sends a reader to a page (and a heading of it) must name
    one that exists."""
    cite = re.compile(r"((?:docs/[\w/.-]+\.md)|README(?:\.md)?)(?:,)?(?: \"([^\"]+)\"| '([^']+)')?")
    broken = []
    for path in project_files(".py"):
        text = re.sub(r"\s*\n\s*#?\s*", " ", path.read_text(errors="replace"))  # one line, comment marks dropped
        for m in cite.finditer(text):
            doc = m.group(1)
            page = ROOT / ("README.md" if doc.startswith("README") else doc)
            if not page.is_file():
                broken.append(f"{path.relative_to(ROOT)}: {doc}")
                continue
            heading = m.group(2) or m.group(3)
            if heading and heading not in {h.replace("`", "") for h in headings(page)}:
                broken.append(f"{path.relative_to(ROOT)}: {doc}, {heading!r}")
    assert not broken, "citations of missing pages or headings:\n" + "\n".join(broken)


def documented_command_lines() -> list[tuple[str, str]]:
    """(page, command line) of every `tesseract4d ...` line in a shell block of the README, the docs
    pages (not docs/research: it tells what was run then) and the model cards."""
    pages = [README, *sorted((ROOT / "docs").glob("*.md")), *MODEL_CARDS]
    found = []
    for page in pages:
        for block in re.findall(r"```(?:bash|sh|console)?\n(.*?)```", page.read_text(), flags=re.S):
            for line in block.replace("\\\n", " ").splitlines():
                line = line.split(" #")[0].strip()
                match = re.search(r"(?:^|\s|/)tesseract4d (\S.*)", line)
                if match and not line.startswith("#"):
                    found.append((str(page.relative_to(ROOT)), re.split(r"&&|\||>", match.group(1))[0].strip()))
    return found


def test_every_documented_command_parses_with_todays_cli_without_a_deprecated_spelling(capsys):
    import shlex

    from tesseract4d.cli import GROUPS, build_parser

    lines = documented_command_lines()
    assert len(lines) > 30, "the documentation's command lines were not found"
    bad = []
    for page, line in lines:
        words = shlex.split(line)
        if not words or words[0].startswith("-"):  # `tesseract4d --help`, `tesseract4d --version`
            continue
        key = tuple(words[:2]) if words[0] in GROUPS else (words[0],)
        parser, _ = build_parser(key)
        try:
            parser.parse_args(words[len(key):])
        except SystemExit as stop:
            if stop.code == 0:  # --help or --set list: it prints and ends
                capsys.readouterr()
                continue
            bad.append(f"{page}: tesseract4d {line}\n    {capsys.readouterr().err.strip().splitlines()[-1]}")
            continue
        if "deprecated" in capsys.readouterr().err:
            bad.append(f"{page}: tesseract4d {line}\n    uses a deprecated spelling")
    assert not bad, "documented commands today's CLI refuses:\n" + "\n".join(bad)
