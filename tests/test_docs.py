"""The algorithm pages the source cites exist, with the cited sections; no citation leaves the repository."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "src" / "napari_dslrxr"
ALGORITHMS = ROOT / "docs" / "algorithms"

# "docs/algorithms/psf.md, section 'Model'" or "docs: simulation.md, 'Mirror ghost'", possibly with
# a docstring line break (and its indentation) inside the section name.
CITATION = re.compile(r"docs(?:/algorithms/|: )(\w+)\.md(?:``)?(?:,\s*(?:sections?\s+)?'([^']+)'"
                      r"(?:\s+and\s+'([^']+)')?)?")


def _python_files():
    return sorted(SOURCE.rglob("*.py"))


def _headings(page: Path) -> set[str]:
    return {line.lstrip("#").strip() for line in page.read_text(encoding="utf-8").splitlines()
            if line.startswith("#")}


def test_every_cited_page_and_section_exists():
    cited = 0
    for path in _python_files():
        text = path.read_text(encoding="utf-8")
        # join docstring and comment continuation lines so a section name may wrap
        flat = re.sub(r"\n\s*#?\s*", " ", text)
        for match in CITATION.finditer(flat):
            page = ALGORITHMS / f"{match.group(1)}.md"
            assert page.is_file(), f"{path.relative_to(ROOT)} cites {page.relative_to(ROOT)}, which does not exist"
            for section in filter(None, match.groups()[1:]):
                assert section in _headings(page), \
                    f"{path.relative_to(ROOT)} cites section {section!r} of {page.name}, which has no such heading"
            cited += 1
    assert cited >= 25  # the algorithm notes are cited from the code, not only present


def test_no_citation_of_notes_outside_the_repository():
    # our own files only: not a virtual environment the benchmarks create (pysaber's)
    others = [p for folder in ("benchmarks", "tests", "scripts") for p in (ROOT / folder).rglob("*.py")
              if p.resolve() != Path(__file__).resolve()
              and not any(part.startswith(".venv") for part in p.relative_to(ROOT).parts)]
    for path in [*_python_files(), *others]:
        text = path.read_text(encoding="utf-8")
        for bad in ("shared/notes", "notes/", "notes §", "notes section", "notes, section", "notes ``",
                    "notes' "):
            assert bad not in text, f"{path.relative_to(ROOT)} cites notes outside the repository: {bad!r}"


def test_index_links_every_page_and_readme_links_the_index():
    index = (ROOT / "docs" / "README.md").read_text(encoding="utf-8")
    pages = sorted(p.name for p in ALGORITHMS.glob("*.md"))
    assert {"impulse.md", "flatfield.md", "region.md", "deconvolution.md", "dynamic_range.md", "contrast.md",
            "metrics.md", "psf.md", "simulation.md", "diagnosis.md"} <= set(pages)
    for name in pages:
        assert f"(algorithms/{name})" in index, name
    for link in re.findall(r"\]\(([^)#]+\.md)\)", index):
        assert (ROOT / "docs" / link).is_file(), link
    for page in ALGORITHMS.glob("*.md"):  # links between pages resolve
        for link in re.findall(r"\]\(([^)#]+\.md)\)", page.read_text(encoding="utf-8")):
            assert (page.parent / link).is_file(), (page.name, link)
    assert "(docs/README.md)" in (ROOT / "README.md").read_text(encoding="utf-8")


def test_documented_defaults_match_the_parameter_classes():
    """Every default in the pages' parameter tables is the dataclass default."""
    from napari_dslrxr.core.params import PipelineParams, params_to_dict

    defaults = params_to_dict(PipelineParams())
    pages = {"impulse": "impulse.md", "flatfield": "flatfield.md", "region": "region.md",
             "dynamic_range": "dynamic_range.md", "contrast": "contrast.md", "exposure": "exposure_index.md"}
    checked = 0
    for section, name in pages.items():
        rows = re.findall(r"^\| `(\w+)` \| ([^|]+) \|", (ALGORITHMS / name).read_text(encoding="utf-8"), re.M)
        documented = dict(rows)
        for key, value in defaults[section].items():
            assert key in documented, f"{name}: no row for {section}.{key}"
            text = documented[key].strip().split(" ")[0].replace("\u00a0", "")
            if isinstance(value, bool):
                assert text == str(value).lower(), (section, key, text)
            elif isinstance(value, (int, float)):
                assert float(text.replace(",", "")) == float(value), (section, key, text)
            checked += 1
    assert checked >= 40


def test_module_and_test_paths_named_in_the_pages_exist():
    pages = [ROOT / "docs" / "README.md", *ALGORITHMS.glob("*.md")]
    named = 0
    for page in pages:
        text = page.read_text(encoding="utf-8")
        for module in re.findall(r"`(core/[\w/]+\.py)", text):
            assert (SOURCE / module).is_file(), f"{page.name} names {module}, which does not exist"
            named += 1
        for test in re.findall(r"`(tests/[\w/]+\.py)`", text):
            assert (ROOT / test).is_file(), f"{page.name} names {test}, which does not exist"
    assert named >= 20
