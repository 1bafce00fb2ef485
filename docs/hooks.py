"""MkDocs hooks (mkdocs.yml `hooks:`): what the pages show of the code is read from the code when
the site is built.

- `<!-- ports: NAME -->` in a page becomes the table of the exported ports of the Diagram NAME of
  `ms_drake.experiments.ports.concept_diagrams()` (direction, name, type);
- `<!-- picture: NAME -->` becomes its Graphviz picture (an SVG generated into the site), or a
  note when Graphviz's `dot` is not installed (the build does not need it);
- `<!-- exports -->` becomes the table of the names `ms_drake` exports, linked to their API pages.
"""

from __future__ import annotations

import importlib
import posixpath
import re

from mkdocs.structure.files import File

import ms_drake
from ms_drake.experiments.ports import concept_diagrams, graphviz_svg, ports_table

PICTURE_DIR = "diagrams"
#: The modules the API reference renders (identifiers that cross-references can link to).
REFERENCE_MODULES = (
    "ms_drake.scenario", "ms_drake.station.station", "ms_drake.station.hardware", "ms_drake.policies.bin_search",
    "ms_drake.policies.shelf_search", "ms_drake.policies.rearrange", "ms_drake.scenes.layouts",
    "ms_drake.experiments.rollout", "ms_drake.experiments.harness", "ms_drake.experiments.reproduce",
    "ms_drake.config_files",
)
MARKER = re.compile(r"<!-- (ports|picture): (\w+) -->|<!-- exports -->")

_diagrams: dict | None = None
_pictures: set[str] = set()


def _get_diagrams() -> dict:
    global _diagrams
    if _diagrams is None:
        _diagrams = concept_diagrams()
    return _diagrams


def on_files(files, config):
    """The diagrams' SVG pictures as generated files of the site (none without Graphviz)."""
    _pictures.clear()
    for name, system in _get_diagrams().items():
        svg = graphviz_svg(system)
        if svg is not None:
            files.append(File.generated(config, f"{PICTURE_DIR}/{name}.svg", content=svg))
            _pictures.add(name)
    return files


def _exports_table() -> str:
    lines = ["| name | defined in |", "|---|---|"]
    for name in sorted(ms_drake._EXPORTS, key=str.lower):
        module = getattr(importlib.import_module(ms_drake._EXPORTS[name]), name).__module__
        shown = f"[`{name}`][{module}.{name}]" if module in REFERENCE_MODULES else f"`{name}`"
        lines.append(f"| {shown} | `{module}` |")
    return "\n".join(lines) + "\n"


def on_page_markdown(markdown, page, config, files):
    if "<!-- " not in markdown:
        return markdown
    here = posixpath.dirname(page.file.src_uri)

    def replace(m):
        kind, name = m.group(1), m.group(2)
        if kind is None:
            return _exports_table()
        diagrams = _get_diagrams()
        if name not in diagrams:
            raise ValueError(f"{page.file.src_uri}: no diagram {name!r}; the diagrams are {', '.join(diagrams)}")
        if kind == "ports":
            return ports_table(diagrams[name])
        if name in _pictures:
            src = posixpath.relpath(f"{PICTURE_DIR}/{name}.svg", here or ".")
            return f"[![The {name} Diagram]({src})]({src})"
        return (f"*(The picture of the {name} Diagram needs Graphviz's `dot`, which is not installed here; "
                "`ms-drake diagram SCENARIO --out FILE.dot` writes the station's Graphviz source.)*")

    return MARKER.sub(replace, markdown)
