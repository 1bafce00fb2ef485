"""The documentation site (mkdocs.yml, docs/): it builds with warnings as errors, its API pages
carry the docstrings, its port tables come from the code, and every complete program in its pages
runs as written.

Convention of the pages: a ```python block is a complete program (run here, or, the getting
started search, the README's example that tests/test_readme.py runs); a ```py block is a snippet
(it names a tested script or test instead)."""

import html
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from ms_drake.experiments import ports
from ms_drake.policies.bin_search import BinSearchConfig

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
# the site's own pages: the hand-written ones, the results pages by chapter and the per-table pages
# `ms-drake reproduce` writes (not the records in docs/results/ nor the pre-registrations in docs/prereg/)
PAGES = sorted([*DOCS.glob("*.md"), *DOCS.glob("tutorials/*.md"), *DOCS.glob("reference/*.md"),
                *DOCS.glob("results/*.md"), *DOCS.glob("results/*/*.md")])
# every markdown document of the repository's documentation, for the length budget
ALL_DOCS = sorted([ROOT / "README.md", *DOCS.rglob("*.md")])
DOCS_LINE_BUDGET = 3000
# the records of the figures shown: gzip'd in docs/results/records/<chapter>/, each named on its chapter page
# (`records/...`, shell braces allowed, a folder ending in /), and beside the per-table pages
RECORDS = DOCS / "results" / "records"
RECORD_SUFFIXES = (".jsonl", ".json", ".gz", ".npz")
RECORDS_BUDGET = 15_000_000  # bytes of records under docs/
PYTHON_BLOCK = re.compile(r"```python\n(.*?)```", re.S)


def _text(html_file: Path) -> str:
    """The visible text of a built page, whitespace collapsed."""
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", html_file.read_text())).split())


def _readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    return PYTHON_BLOCK.search(text[text.index("## Using it"):]).group(1)


def test_the_site_builds_with_warnings_as_errors(tmp_path):
    site = tmp_path / "site"
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
                          "-d", str(site)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    # The API page of the bin search holds BinSearchConfig's docstring.
    api = _text(site / "reference" / "bin_search" / "index.html")
    first = BinSearchConfig.__doc__.split("\n\n")[0]
    assert first.startswith("One bin search")
    assert "".join(first.replace("`", "").split()) in "".join(api.split())  # as text: code spans, line breaks
    # The concepts page's port tables are the code's ports.
    concepts = _text(site / "concepts" / "index.html")
    for name in ("floating_jaw.force_limit", "overhead.label_image", "yumi_left_suction.suction", "occupancy"):
        assert name in concepts
    assert "list[RigidTransform]" in concepts and "types.InstanceMasks" in concepts
    assert "<!-- ports" not in (site / "concepts" / "index.html").read_text()
    if ports.shutil.which("dot"):
        assert (site / "diagrams" / "bin_search.svg").read_text().lstrip().startswith("<svg")
    # the package's exports link to their API pages
    assert 'href="bin_search/#ms_drake.policies.bin_search.MakeBinSearchController"' in \
        (site / "reference" / "index.html").read_text()


def test_the_docs_are_short_and_name_no_internal_history():
    lines = {p: len(p.read_text().splitlines()) for p in ALL_DOCS}
    assert sum(lines.values()) <= DOCS_LINE_BUDGET, (
        f"README.md and docs/**/*.md hold {sum(lines.values())} lines (budget {DOCS_LINE_BUDGET}); the longest: "
        + ", ".join(f"{p.relative_to(ROOT)} {n}" for p, n in sorted(lines.items(), key=lambda kv: -kv[1])[:5]))
    for page in [ROOT / "README.md", *PAGES]:
        text = page.read_text()
        found = re.search(r"\bissues?\b|#\d{1,4}\b|\bsessions?\b|BENCHMARKS\.md", text, re.I)
        assert not found, f"{page.relative_to(ROOT)}: {found.group(0)!r} (internal issue numbers, work history)"


def test_docs_keep_only_the_records_of_the_results_pages_within_budget():
    assert not (DOCS / "data").exists(), "docs/data/ is gone: a figure's records go to docs/results/records/<chapter>/"
    records = [p for p in DOCS.rglob("*") if p.is_file() and p.name.endswith(RECORD_SUFFIXES)]
    total = sum(p.stat().st_size for p in records)
    assert total <= RECORDS_BUDGET, (
        f"records under docs/ take {total / 1e6:.1f} MB (budget {RECORDS_BUDGET / 1e6:.0f} MB); the largest: "
        + ", ".join(f"{p.relative_to(ROOT)} {p.stat().st_size / 1e6:.1f} MB"
                    for p in sorted(records, key=lambda p: -p.stat().st_size)[:5]))


def _braces(pattern: str) -> list[str]:
    """A shell brace pattern's names: "a_{x,y}{,_z}" -> a_x, a_x_z, a_y, a_y_z."""
    m = re.search(r"\{([^{}]*)\}", pattern)
    if not m:
        return [pattern]
    return [name for alt in m.group(1).split(",") for name in _braces(pattern[:m.start()] + alt + pattern[m.end():])]


def test_every_kept_record_is_named_on_a_results_page_and_every_named_one_exists():
    named = set()
    for page in sorted((DOCS / "results").glob("*.md")):
        for pattern in re.findall(r"`(records/[^`\s]+)`", page.read_text()):
            for name in _braces(pattern):
                path = DOCS / "results" / name
                assert path.exists(), f"{page.relative_to(ROOT)} names {name}, which is not in docs/results/"
                named |= {path} if path.is_file() else set(path.rglob("*"))
    kept = {p for p in RECORDS.rglob("*") if p.is_file()}
    assert all(p.name.endswith(".gz") for p in kept), "records are kept gzip'd"
    unnamed = sorted(str(p.relative_to(DOCS / "results")) for p in kept - named)
    assert not unnamed, f"records no results page names (a figure gone: remove them): {unnamed[:10]}"


def _programs():
    readme = _readme_example()
    for page in PAGES:
        for k, m in enumerate(PYTHON_BLOCK.finditer(page.read_text())):
            if m.group(1) != readme:
                yield pytest.param(page, m.group(1), id=f"{page.relative_to(DOCS)}#{k}")


def test_the_getting_started_search_is_the_readme_s_tested_example():
    assert _readme_example() in PYTHON_BLOCK.findall((DOCS / "getting-started.md").read_text())


@pytest.mark.parametrize("page, code", list(_programs()))
def test_the_complete_programs_of_the_pages_run_as_written(page, code, capsys):
    exec(compile(code, str(page), "exec"), {"__name__": "__main__"})
    assert capsys.readouterr().out.strip()


class _Two(LeafSystem):
    def __init__(self):
        super().__init__()
        self.DeclareVectorInputPort("command", 3)
        self.DeclareAbstractOutputPort("masks", lambda: AbstractValue.Make((1, 2)), lambda c, o: None)


def _hooks():
    spec = importlib.util.spec_from_file_location("docs_hooks", DOCS / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class _Page:
    class file:
        src_uri = "concepts.md"


def test_the_hook_tables_ports_and_notes_a_missing_graphviz(monkeypatch):
    hooks = _hooks()
    monkeypatch.setattr(hooks, "_diagrams", {"two": _Two()})
    assert ports.port_rows(hooks._diagrams["two"]) == [ports.PortRow("input", "command", "vector[3]"),
                                                       ports.PortRow("output", "masks", "tuple")]
    monkeypatch.setattr(ports.shutil, "which", lambda name: None)
    monkeypatch.setattr(hooks, "graphviz_svg", lambda system: ports.graphviz_svg(system))
    files = []
    assert hooks.on_files(files, config=None) == []  # no dot: no pictures, no failure
    md = hooks.on_page_markdown("<!-- ports: two -->\n\n<!-- picture: two -->\n", _Page, None, None)
    assert "| input | `command` | `vector[3]` |" in md and "needs Graphviz's `dot`" in md
    with pytest.raises(ValueError, match="no diagram 'three'"):
        hooks.on_page_markdown("<!-- ports: three -->", _Page, None, None)
