"""`ms-drake reproduce NAME` (ms_drake.experiments.reproduce): the registry of the twelve recipes, its
errors, and each recipe end to end at a tiny size, run twice: the second run finds every record in
place and does no new work."""

from __future__ import annotations

from pathlib import Path

import pytest

from ms_drake.errors import MsDrakeError
from ms_drake.experiments import reproduce as reproduce_module
from ms_drake.experiments.reproduce import RECIPES, ReproduceError, list_recipes, reproduce

NAMES = ("table_2_1", "table_3_1", "fig_4_2", "table_b_1", "table_6_1", "table_6_3", "table_8_1", "table_9_1",
         "table_9_2", "table_c_1", "fig_7_4", "table_8_2")

# name -> (tiny counts, other reproduce() arguments): each test takes seconds to half a minute.
TINY = {
    "table_2_1": ({"objects": 3, "grasps": 2, "trials": 1}, {}),
    "table_3_1": ({"objects": 3, "grasps": 2, "trials": 1}, {}),
    # seed 4 of the household-object heaps is improvable (tests/data/push_heaps_ycb): one heap to drop
    "fig_4_2": ({"heaps": 1}, {"seed_start": 4}),
    "table_b_1": ({"images": 3}, {}),
    "table_6_1": ({"scenes": 2}, {}),
    "table_6_3": ({"scenes": 1, "objects": 1}, {}),
    "table_8_1": ({"test_images": 32, "ood_images": 32}, {}),
    "table_9_1": ({"scenes": 1, "occluders": [4]}, {}),
    # one scene per policy (seed 2, the first of the 8 / 10 / 12 cycle: 8 occluders), one action each
    "table_9_2": ({"scenes": 1, "horizon": 1}, {"seed_start": 2}),
    # the bin searches: one heap per selector (and per N), through one pool, heaps shared
    "table_c_1": ({"heaps": 1}, {}),
    "fig_7_4": ({"heaps": 1}, {}),
    "table_8_2": ({"heaps": 1}, {}),
}


def test_list_recipes_names_all_twelve():
    recipes = list_recipes()
    assert [r.name for r in recipes] == list(NAMES)
    for r in recipes:
        assert r.title and r.reference, r.name
        assert set(r.small) == set(r.full), r.name
        assert all(r.small[k] <= r.full[k] for k in r.small), r.name
        assert r.total(r.small) > 0


def test_unknown_name_size_or_count_names_the_choices(tmp_path):
    with pytest.raises(MsDrakeError, match=r"unknown recipe 'table_9_9'; choose one of table_2_1, .*table_8_2"):
        reproduce("table_9_9", out=tmp_path)
    with pytest.raises(ReproduceError, match=r"unknown size 'medium' .*choose one of small, full"):
        reproduce("table_9_1", size="medium", out=tmp_path)
    with pytest.raises(ReproduceError, match=r"sizes heaps unknown for recipe table_9_1; give some of scenes, occl"):
        reproduce("table_9_1", sizes={"heaps": 3}, out=tmp_path)


def _records(folder: Path, name: str) -> dict:
    """Every record file under OUT/NAME (the markdown and figures apart): lines of a JSON-lines file,
    bytes of any other."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name != f"{name}.md" and p.suffix != ".png":
            out[str(p.relative_to(folder))] = p.read_text().count("\n") if p.suffix == ".jsonl" else p.stat().st_size
    return out


def _table(md: str) -> list[list[str]]:
    """The cells of the markdown table's rows (header and rule apart)."""
    rows = [line.strip("|").split("|") for line in md.splitlines() if line.startswith("| ")]
    return [[c.strip() for c in r] for r in rows[1:]]


@pytest.mark.parametrize("name", TINY)
def test_recipe_runs_end_to_end_and_resumes(name, tmp_path, monkeypatch):
    monkeypatch.setattr(reproduce_module, "BOOTSTRAP_RECOMPUTED", 20)  # the LOO table / COCO AP per resample
    sizes, kwargs = TINY[name]
    calls = []
    md = reproduce(name, sizes=sizes, out=tmp_path, progress=lambda done, total: calls.append((done, total)), **kwargs)
    assert md == tmp_path / name / f"{name}.md"
    text = md.read_text()
    assert RECIPES[name].title in text
    assert "| | metric | ours | 95 % interval | reference |" in text
    assert "Machine: " in text and "CPUs" in text and "Command: `reproduce(" in text
    rows = _table(text)
    # ours beside the reference's figure on at least one row
    assert any(r[2] != "-" and r[4] != "-" for r in rows), text
    assert calls and calls[-1][0] == calls[-1][1] and all(d <= t for d, t in calls)
    for line in text.splitlines():
        if line.startswith("!["):
            assert (md.parent / line.split("(")[1].rstrip(")")).is_file()
    records = _records(tmp_path / name, name)
    assert records

    again = []
    reproduce(name, sizes=sizes, out=tmp_path, progress=lambda done, total: again.append((done, total)), **kwargs)
    assert _records(tmp_path / name, name) == records  # nothing new: every item was found in the records
    assert again[-1][0] == again[-1][1]
