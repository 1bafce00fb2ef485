"""Bad input to the ms-drake command: one clear error line, exit status 2, no traceback, and no work
started: training never writes into the shipped weights unasked, weights files are loaded before any
worker starts, result files are read by one checking reader, and an --out that cannot be written is
refused up front.

The commands run in this process (ms_drake.cli.main with sys.argv set): an exception that escaped
main() would fail the test, which is what "no traceback" means here."""

import gzip
import json
import os
import runpy
import sys
from pathlib import Path

import pytest

from ms_drake import cli
from ms_drake.errors import RecordFileError
from ms_drake.experiments.records import read_record_file
from ms_drake.paths import model_path

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


def assert_one_error(code, err, *needles):
    assert code == 2, err
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for n in needles:
        assert str(n) in lines[0], (n, lines[0])


def _leaves(command, path=()):
    subs = getattr(command, "commands", None)
    if subs:
        for name, sub in subs.items():
            yield from _leaves(sub, path + (name,))
    else:
        yield path, command


def _commands():
    import typer

    return list(_leaves(typer.main.get_command(cli.app)))


# -- 1. training writes into models/weights/ only when told to -----------------------------------------


TRAIN = [path for path, _ in _commands() if path[0] == "train"]


def test_every_train_command_is_checked():
    assert {p[1] for p in TRAIN} >= {"occupancy", "shelf-occupancy", "segmentation", "collision", "matcher"}


@pytest.mark.parametrize("path", TRAIN, ids=" ".join)
def test_train_default_out_is_outside_the_shipped_weights(path):
    command = dict(_commands())[path]
    out = next(p for p in command.params if "--out" in p.opts)
    default = Path(out.default).resolve()
    shipped = model_path("weights").resolve()
    assert shipped not in default.parents, default
    assert str(out.default).startswith("out/weights/")
    assert any("--overwrite-shipped" in p.opts for p in command.params)


@pytest.mark.parametrize("path", TRAIN, ids=" ".join)
def test_train_refuses_the_shipped_weights_folder(capsys, tmp_path, path):
    target = model_path("weights") / f"smoke_{path[1]}.pt"
    before = sorted(model_path("weights").iterdir())
    code, _, err = run_cli(capsys, *path, "--data", tmp_path, "--out", target)
    assert_one_error(code, err, str(target), "--overwrite-shipped")
    assert sorted(model_path("weights").iterdir()) == before  # nothing written, not even a checkpoint


DEVICE_TRAIN = [path for path in TRAIN if any("--device" in p.opts for p in dict(_commands())[path].params)]


def test_the_learned_models_train_on_a_chosen_device():
    assert {p[1] for p in DEVICE_TRAIN} >= {"occupancy", "segmentation", "collision", "matcher"}


@pytest.mark.parametrize("path", DEVICE_TRAIN, ids=" ".join)
def test_train_on_cuda_without_a_gpu_is_one_error(capsys, tmp_path, path):
    import torch  # noqa: PLC0415 - the CLI's other tests need no torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    out = tmp_path / "w" / "m.pt"
    code, _, err = run_cli(capsys, *path, "--data", tmp_path, "--out", out, "--device", "cuda")
    assert_one_error(code, err, "'cuda'", "--device cpu", "--device auto")
    assert not out.parent.exists()  # nothing started


def test_overwrite_shipped_lets_the_check_pass(tmp_path):
    cli._need_training_out(model_path("weights") / "occupancy.pt", overwrite_shipped=True)  # no exit
    cli._need_training_out(tmp_path / "w.pt", overwrite_shipped=False)


# -- 2. weights files are loaded once, in the parent, before anything runs --------------------------------


def _weights_files(tmp_path, other: str) -> dict:
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"these bytes are no torch checkpoint\x00\x01")
    return {"garbage": (garbage, "cannot be read"), "other": (model_path(f"weights/{other}"), str(other)),
            "missing": (tmp_path / "missing.pt", "not found")}


# (command line with W for the weights file, a shipped file holding another network)
WEIGHTS_OPTIONS = [
    (["bench", "search", "--policy", "xray", "--heaps", "1", "--set", "occupancy_weights=W", "--out", "OUT/r.jsonl"],
     "matcher.pt"),
    (["train", "occupancy", "--data", "OUT", "--init", "W", "--out", "OUT/o.pt"], "matcher.pt"),
    (["train", "segmentation", "--data", "OUT", "--init", "W", "--out", "OUT/s.pt"], "occupancy.pt"),
    (["train", "collision", "--data", "OUT", "--encoders", "W", "--out", "OUT/c.pt"], "occupancy.pt"),
    (["bench", "occupancy", "--data", "OUT", "--weights", "W"], "segmentation.pt"),
    (["bench", "shelf-occupancy", "--data", "OUT", "--weights", "W"], "occupancy.pt"),
    (["bench", "collision", "--method", "net", "--scenes", "1", "--weights", "W"], "occupancy.pt"),
    (["bench", "mppi", "--method", "net", "--scenes", "1", "--weights", "W"], "shelf_occupancy.pt"),
    (["bench", "segmentation", "--backend", "learned", "--images", "1", "--weights", "W"], "matcher.pt"),
    (["bench", "target-detection", "--backend", "learned", "--images", "1", "--weights", "W", "--out",
      "OUT/t.json"], "occupancy.pt"),
]


def test_every_weights_option_is_tested():
    tested = {(args[0], args[1], next(a for a in args if a in ("--set", "--init", "--encoders", "--weights")))
              for args, _ in WEIGHTS_OPTIONS}
    for path, command in _commands():
        for p in command.params:
            if set(p.opts) & {"--weights", "--occupancy-weights", "--init", "--encoders"}:
                assert (*path, p.opts[0]) in tested, f"{' '.join(path)} {p.opts[0]}: add it to WEIGHTS_OPTIONS"


@pytest.mark.parametrize("case", ["garbage", "other", "missing"])
@pytest.mark.parametrize("args, other", WEIGHTS_OPTIONS, ids=lambda x: " ".join(x[:2]) if isinstance(x, list) else "")
def test_weights_that_do_not_load_fail_at_start(capsys, tmp_path, args, other, case):
    weights, needle = _weights_files(tmp_path, other)[case]
    argv = [str(weights) if a == "W" else a.replace("=W", f"={weights}").replace("OUT", str(tmp_path)) for a in args]
    code, out, err = run_cli(capsys, *argv)
    assert_one_error(code, err, weights.name, "ms-drake train")
    assert needle in err or case == "other", err
    if case == "other":
        assert "does not hold" in err or "is not a" in err or "not a" in err, err
    assert not (tmp_path / "r.jsonl").exists()  # bench search: no rollout ran, none recorded as worker_died


# -- 3. result files: one reader, one error per kind of damage -------------------------------------------


def _records(name: str, n: int = 3) -> list[str]:
    return (DOCS / name).read_text().splitlines()[:n]


# command line with F for the file(s), the docs file whose records it reads, a field it needs
READERS = [
    (["bench", "plot", "F", "--out", "OUT/plots"], "demo_xray_50.jsonl", "actions"),
    (["bench", "replay", "F"], "demo_xray_50.jsonl", "objects"),
    (["bench", "paired", "F", "F"], "demo_xray_50.jsonl", "success"),
    (["bench", "push-table", "F"], "push_bench.jsonl", "overall_gain"),
    (["bench", "shelf-table", "F"], "shelf_dar.jsonl", "steps"),
    (["bench", "shelf-physics-table", "F"], "shelf_physics_der3.jsonl", "occluders"),
    (["bench", "rearrange", "--table", "--out", "F"], "rearrange_net.jsonl", "method"),
]


def _damaged(tmp_path, source: str, field: str, case: str) -> Path:
    lines = _records(source)
    f = tmp_path / "records.jsonl"
    if case == "empty":
        f.write_text("\n")
    elif case == "corrupt":
        f.write_text("\n".join([lines[0], '{"seed": 3, "policy": "xr', *lines[1:]]) + "\n")
    elif case == "no_field":
        rec = json.loads(lines[1])
        del rec[field]
        f.write_text("\n".join([lines[0], json.dumps(rec), lines[2]]) + "\n")
    else:
        f.write_text("\n".join(lines) + "\n")
    return f


def _run_reader(capsys, tmp_path, args, f):
    argv = [str(f) if a == "F" else a.replace("OUT", str(tmp_path)) for a in args]
    if argv[0].startswith("sims/"):
        saved = sys.argv
        sys.argv = [argv[0], *argv[1:]]
        try:
            runpy.run_path(str(ROOT / argv[0]), run_name="__main__")
            code = 0
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        finally:
            sys.argv = saved
        out, err = capsys.readouterr()
        return code, out, err
    return run_cli(capsys, *argv)


@pytest.mark.parametrize("case, needle", [("empty", "no records"), ("corrupt", "line 2"),
                                          ("no_field", "line 2")])
@pytest.mark.parametrize("args, source, field", READERS, ids=lambda x: " ".join(x[:2]) if isinstance(x, list) else "")
def test_a_bad_result_file_is_one_clear_error(capsys, tmp_path, args, source, field, case, needle):
    f = _damaged(tmp_path, source, field, case)
    text = f.read_text()
    code, out, err = _run_reader(capsys, tmp_path, args, f)
    assert_one_error(code, err, str(f), needle)
    if case == "no_field":
        assert repr(field) in err
    assert f.read_text() == text  # a reader never rewrites a damaged file


@pytest.mark.parametrize("args, source, field", READERS[:1] + READERS[3:5],
                         ids=lambda x: " ".join(x[:2]) if isinstance(x, list) else "")
def test_a_missing_result_file_names_the_command_that_writes_it(capsys, tmp_path, args, source, field):
    code, out, err = _run_reader(capsys, tmp_path, args, tmp_path / "none.jsonl")
    assert_one_error(code, err, "none.jsonl", f"ms-drake {args[0]} " if args[0] != "bench" else "ms-drake bench")


def test_read_record_file(tmp_path):
    f = tmp_path / "r.jsonl"
    f.write_text('{"seed": 1}\n\n{"seed": 2}\n{"seed": 3, "pol')  # a torn last line: killed mid-write
    assert [r["seed"] for r in read_record_file(f)] == [1, 2]
    assert f.read_text().endswith('"pol')  # reading leaves the file alone
    assert [r["seed"] for r in read_record_file(f, resume=True)] == [1, 2]
    assert f.read_text() == '{"seed": 1}\n\n{"seed": 2}\n'  # resuming cuts it, the next line starts clean
    f.write_text('{"seed": 1}\n{"seed": 2, "pol\n{"seed": 3}\n')
    with pytest.raises(RecordFileError, match=r"r.jsonl, line 2: not a JSON record"):
        read_record_file(f, resume=True)
    f.write_text('{"seed": 1}\n[1, 2]\n')
    with pytest.raises(RecordFileError, match="line 2: not a JSON record .*list"):
        read_record_file(f)
    f.write_text('{"seed": "one"}\n')
    with pytest.raises(RecordFileError, match="line 1: seed 'one' is not an integer"):
        read_record_file(f)
    f.write_text('{"seed": 1}\n')
    with pytest.raises(RecordFileError, match="line 1: the record has no 'policy'.*ms-drake bench search"):
        read_record_file(f, ("seed", "policy"), "bench search")
    assert read_record_file(tmp_path / "none.jsonl", resume=True) == []
    with pytest.raises(RecordFileError, match="no such result file; make it with `ms-drake bench shelf"):
        read_record_file(tmp_path / "none.jsonl", writer="bench shelf")
    f.write_text("")
    assert read_record_file(f, resume=True) == []
    with pytest.raises(RecordFileError, match="no records"):
        read_record_file(f)
    # the repository's records are gzipped: read as they are, a torn last line dropped, the file left alone
    g = tmp_path / "r.jsonl.gz"
    packed = gzip.compress(b'{"seed": 4}\n{"seed": 5, "pol')
    g.write_bytes(packed)
    assert [r["seed"] for r in read_record_file(g, resume=True)] == [4]
    assert g.read_bytes() == packed
    g.write_bytes(b'{"seed": 4}\n')  # named .gz, not compressed
    with pytest.raises(RecordFileError, match="r.jsonl.gz: not a JSON-lines result file"):
        read_record_file(g)


def test_resuming_a_file_with_a_corrupt_line_stops_before_any_rollout(capsys, tmp_path):
    out = tmp_path / "r.jsonl"
    lines = _records("demo_xray_50.jsonl", 2)
    out.write_text("\n".join([lines[0], "garbage", lines[1]]) + "\n")
    code, _, err = run_cli(capsys, "bench", "search", "--policy", "largest", "--config", "ch7", "--heaps", "1",
                           "--out", out)
    assert_one_error(code, err, str(out), "line 2")
    assert len(out.read_text().splitlines()) == 3


# -- 4. an --out that cannot be written: one line naming it, before any work -----------------------------


def _dummy_args(command, tmp_path, tested: str) -> list[str]:
    """The command's required arguments and options but `tested` with values that parse (the guard on
    the output options runs before the command's body, so these values are never used)."""
    args = []
    for p in command.params:
        if not p.required or tested in p.opts:
            continue
        name = str(getattr(getattr(p, "type_descriptor", None), "annotation", ""))
        value = "1" if "int" in name else "1.0" if "float" in name else str(tmp_path / "in.jsonl")
        args += [value] if p.param_type_name == "argument" else [p.opts[0], value]
    return args


WRITERS = [(path, command) for path, command in _commands()
           if any(set(p.opts) & set(cli.OUTPUT_OPTIONS) for p in command.params)]


@pytest.mark.parametrize("path, command", WRITERS, ids=lambda x: " ".join(x) if isinstance(x, tuple) else "")
def test_every_output_under_a_regular_file_is_refused(capsys, tmp_path, path, command):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    outputs = [p.opts[0] for p in command.params if set(p.opts) & set(cli.OUTPUT_OPTIONS)]
    for option in outputs:
        bad = blocker / "sub" / ("x.jsonl" if option == "--out" else "x.json")
        code, _, err = run_cli(capsys, *path, *_dummy_args(command, tmp_path, option), option, bad)
        assert_one_error(code, err, option, str(bad), "is a file, not a folder")
        assert blocker.read_text() == ""


def test_a_read_only_folder_is_refused(capsys, tmp_path, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    if os.geteuid() == 0:  # root writes anywhere: make os.access answer as for a user
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == ro else real(p, mode))
    for args in (["heaps", "--count", "1", "--out", ro / "h.jsonl"],
                 ["bench", "plot", DOCS / "demo_xray_50.jsonl", "--out", ro / "plots"],
                 ["train", "matcher", "--data", tmp_path, "--out", ro / "m.pt"]):
        code, _, err = run_cli(capsys, *args)
        assert_one_error(code, err, str(ro), "not writable")
    ro.chmod(0o755)


def test_an_os_error_on_a_path_is_one_line(capsys, tmp_path):
    """The last line of defence in main(): an OSError naming a path (here: --out is a folder)."""
    folder = tmp_path / "h.jsonl"
    folder.mkdir()
    code, _, err = run_cli(capsys, "heaps", "--count", "1", "--objects", "1", "--out", folder)
    assert_one_error(code, err, str(folder), "Is a directory")


def test_ctrl_c_ends_any_long_command_with_one_line_and_status_130(tmp_path):
    """A long command interrupted: no traceback, one line saying how to resume, exit 130; what
    finished is in its file."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "s.jsonl"
    cmd = [str(Path(sys.executable).parent / "ms-drake"), "bench", "shelf", "--policy", "dar", "--occluders", "4",
           "--scenes", "500", "--out", str(out)]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=_default_sigint)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 300 and not (out.exists() and out.read_text().count("\n") >= 1):
        time.sleep(0.2)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err[-2000:]
    assert "Traceback" not in err and "run the same command to resume" in err
    assert out.read_text().count("\n") >= 1


def test_a_bad_controller_override_of_the_rearrangement_is_one_error(capsys, tmp_path):
    code, _, err = run_cli(capsys, "bench", "rearrange", "--method", "sdf", "--set", "trajectories=many",
                           "--out", tmp_path / "r.jsonl")
    assert_one_error(code, err, "trajectories=many", "RearrangeParams")
    assert not (tmp_path / "r.jsonl").exists()


def _default_sigint():
    """In the child before exec: Ctrl-C's default action. A process that starts with SIGINT ignored
    keeps it ignored (Python installs its KeyboardInterrupt handler only over the default), and a
    test worker may have inherited or set that."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_shelf_physics_table_names_a_foss_file_given_as_a_physics_one(capsys):
    code, _, err = run_cli(capsys, "bench", "shelf-physics-table", DOCS / "shelf_physics_der3.jsonl",
                           DOCS / "shelf_dar.jsonl")
    assert_one_error(code, err, "shelf_dar.jsonl holds FOSS records", "--foss")
