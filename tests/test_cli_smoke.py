"""Every ms-drake command, listed from the command's own parser: `--help` exits 0, and a tiny real run
where one is cheap (the table commands on copies of the sample records in tests/data). Commands run in this
process (ms_drake.cli.main with sys.argv set), so the package is imported once.

A command added to the CLI fails test_every_command_is_smoke_tested until it is given a tiny run here,
named as run by another test file, or listed in HELP_ONLY with the reason."""

import shutil
import sys
from pathlib import Path

import pytest
import typer

from ms_drake import cli

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "tests" / "data"


def run_cli(capsys, *args):
    """(exit status, stdout, stderr) of `ms-drake ARGS` run in this process."""
    argv = sys.argv
    sys.argv = ["ms-drake", *map(str, args)]
    try:
        cli.main()
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        sys.argv = argv
    out, err = capsys.readouterr()
    return code, out, err


def _walk(command, path=()):
    yield path, command
    for name, sub in (getattr(command, "commands", None) or {}).items():
        yield from _walk(sub, path + (name,))


COMMANDS = [path for path, _ in _walk(typer.main.get_command(cli.app))]
LEAVES = [path for path, c in _walk(typer.main.get_command(cli.app)) if not getattr(c, "commands", None)]

# command -> its tiny run; DOCS/<name> is a copy of tests/data/<name>, OUT a fresh folder
TINY = {
    ("grasp",): ["--object", "procedural/box_000", "--samples", "5", "--robust", "0", "--out", "OUT/grasp"],
    ("reproduce",): ["--list"],
    ("bench", "plot"): ["DOCS/demo_xray_50.jsonl", "--out", "OUT/plots"],
    ("bench", "paired"): ["DOCS/demo_xray_50.jsonl", "DOCS/demo_xray_50.jsonl"],
    ("bench", "push-table"): ["DOCS/push_bench.jsonl", "--json", "OUT/push.json"],
    ("bench", "shelf-table"): ["DOCS/shelf_dar.jsonl"],
    ("bench", "shelf-physics-table"): ["DOCS/shelf_physics_der3.jsonl"],
    ("bench", "rearrange"): ["--table", "--out", "DOCS/rearrange_net.jsonl"],
    ("bench", "shelf-scenes"): ["--count", "2"],
    ("bench", "shelf"): ["--policy", "dar", "--occluders", "4", "--scenes", "1", "--out", "OUT/s.jsonl"],
    ("bench", "shelf-segmentation"): ["--scenes", "1", "--occluders", "4", "--out", "OUT/seg.jsonl"],
    ("bench", "segmentation"): ["--backend", "euclidean", "--images", "1", "--out", "OUT/seg.json"],
    ("bench", "target-detection"): ["--backend", "color", "--images", "1", "--out", "OUT/td.json"],
    ("bench", "mppi"): ["--method", "sdf", "--scenes", "1", "--trajectories", "10", "--horizon", "5", "--steps",
                        "1"],
    ("bench", "collision"): ["--method", "sdf", "--scenes", "1"],
    ("data", "matcher"): ["--heaps", "1", "--heaps-per-shard", "1", "--out", "OUT/matcher"],
    ("data", "occupancy"): ["--count", "1", "--views", "1", "--heaps-per-shard", "1", "--out", "OUT/occupancy"],
    ("data", "shelf"): ["--count", "2", "--shard-size", "2", "--depth-block", "4", "--out", "OUT/shelf"],
}
# commands whose data come from another command: run as a pair in one test
CHAINS = {
    ("train", "segmentation"): (["data", "segmentation", "--count", "1", "--views", "1", "--heaps-per-shard", "1",
                                 "--out", "OUT/d"], ["train", "segmentation", "--data", "OUT/d", "--epochs", "1",
                                                     "--batch", "1", "--out", "OUT/w/s.pt"]),
    ("train", "collision"): (["data", "collision", "--count", "1", "--out", "OUT/d"],
                             ["train", "collision", "--data", "OUT/d", "--epochs", "1", "--out", "OUT/w/c.pt"]),
}
SLOW_CHAINS = {("train", "collision")}  # data collision: a whole shard of scenes, ~15 CPU-s
# commands a tiny run of which is in another test file (through the CLI)
ELSEWHERE = {
    ("demo",): "test_cli.py", ("scene",): "test_cli.py", ("heaps",): "test_cli.py", ("diagram",): "test_cli.py",
    ("bench", "search"): "test_harness.py", ("bench", "replay"): "test_harness.py", ("perceive",): "test_perceive.py",
    ("bench", "config"): "test_harness.py", ("bench", "lift-rates"): "test_lift_rates.py",
}
# --help only, and why
HELP_ONLY = {
    ("pick",): "a full-fidelity pick in physics (minutes)",
    ("bench", "push"): "needs `data push-heaps` heaps (a drop and grasps per heap)",
    ("bench", "push-fidelity"): "YuMi pushes in physics",
    ("bench", "fidelity"): "YuMi grasps in physics",
    ("bench", "shelf-physics"): "the Fetch in physics (minutes per scene)",
    ("bench", "occupancy"): "needs an occupancy dataset with test shards",
    ("bench", "shelf-occupancy"): "needs a shelf dataset with a test split",
    ("data", "push-heaps"): "drops and grasps until stuck (tens of CPU-s per heap)",
    ("data", "grasps"): "robust grasp quality of every object of a set",
    ("train", "occupancy"): "needs a dataset larger than a tiny run makes",
    ("train", "shelf-occupancy"): "needs a shelf dataset with train/ and test/",
    ("train", "matcher"): "needs a matcher dataset larger than a tiny run makes",
    ("data", "segmentation"): "run by the train segmentation chain",
    ("data", "collision"): "run by the train collision chain (slow)",
}


def _argv(args, tmp_path):
    out = []
    for a in args:
        if a.startswith("DOCS/"):
            name = a[len("DOCS/"):]
            if not (tmp_path / name).exists():
                shutil.copy(DOCS / name, tmp_path / name)
            a = str(tmp_path / name)
        out.append(a.replace("OUT", str(tmp_path / "out")))
    return out


def test_every_command_is_smoke_tested():
    assert len(LEAVES) >= 35  # the parser was read
    for path in LEAVES:
        where = [name for name, table in (("TINY", TINY), ("CHAINS", CHAINS), ("ELSEWHERE", ELSEWHERE),
                                          ("HELP_ONLY", HELP_ONLY)) if path in table]
        assert where, f"ms-drake {' '.join(path)}: give it a tiny run in tests/test_cli_smoke.py"
    for path, name in ELSEWHERE.items():
        text = (Path(__file__).parent / name).read_text()
        assert all(f'"{part}"' in text for part in path), (path, name)
    assert set(TINY) | set(CHAINS) | set(ELSEWHERE) | set(HELP_ONLY) <= set(LEAVES)  # no stale entries


@pytest.mark.parametrize("path", COMMANDS, ids=lambda p: " ".join(p) or "ms-drake")
def test_help(capsys, path):
    code, out, err = run_cli(capsys, *path, "--help")
    assert code == 0, err
    assert "Usage:" in out and "--help" in out


@pytest.mark.parametrize("path", list(TINY), ids=" ".join)
def test_tiny_run(capsys, tmp_path, path):
    (tmp_path / "out").mkdir()
    code, out, err = run_cli(capsys, *path, *_argv(TINY[path], tmp_path))
    assert code == 0, f"{out}\n{err}"
    assert out.strip()  # every command reports what it did
    written = [p for p in (tmp_path / "out").rglob("*") if p.is_file()]
    if any(a.startswith("OUT") for a in TINY[path]):
        assert written and all(p.stat().st_size > 0 for p in written), written


@pytest.mark.parametrize("path", [pytest.param(p, marks=pytest.mark.slow) if p in SLOW_CHAINS else p
                                  for p in CHAINS], ids=" ".join)
def test_tiny_chain(capsys, tmp_path, path):
    (tmp_path / "out").mkdir()
    for args in CHAINS[path]:
        code, out, err = run_cli(capsys, *_argv(args, tmp_path))
        assert code == 0, f"{' '.join(args)}\n{out}\n{err}"
    assert (tmp_path / "out" / "w").is_dir() and any((tmp_path / "out" / "w").glob("*.pt"))
