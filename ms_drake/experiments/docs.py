"""Writing measured figures into docs/BENCHMARKS.md from benchmark scripts."""

from __future__ import annotations

from pathlib import Path

HEADER = "# Benchmarks\n\nEvery measured figure, with the command that made it.\n"


def write_benchmark_section(path: str | Path, section: str, text: str) -> None:
    """Replace the `section` ("## Title" heading up to the next "## ") of the benchmarks file
    with `text` (which starts with that heading), or append it when absent."""
    p = Path(path)
    doc = p.read_text() if p.exists() else HEADER
    if section in doc:
        start = doc.index(section)
        nxt = doc.find("\n## ", start + len(section))
        doc = doc[:start] + text + (doc[nxt + 1:] if nxt >= 0 else "")
    else:
        doc = doc.rstrip("\n") + "\n\n" + text
    p.write_text(doc)
