"""ms_drake.config_files: one loader for every task's config (a YAML file or a named setting, then
KEY=VALUE overrides), with one error naming the key or file."""

import dataclasses

import pytest

from ms_drake.config_files import ConfigError, config_dict, load_config
from ms_drake.experiments.push_study import PushStudyConfig
from ms_drake.policies.bin_search import BinSearchConfig
from ms_drake.policies.shelf_search import ShelfSearchConfig


@pytest.mark.parametrize("schema, key, value, read", [
    (BinSearchConfig, "heap.objects", "12", lambda c: c.heap.objects == 12),
    (ShelfSearchConfig, "ablation.suction_lift", "floor", lambda c: c.ablation.suction_lift == "floor"),
    (PushStudyConfig, "ablation.transfer_speed", "2.0", lambda c: c.ablation.transfer_speed == 2.0),  # frozen parts
    (PushStudyConfig, "grasps", "20", lambda c: c.grasps == 20 and c.ablation.sampling == "tilt_bin"),
])
def test_overrides_reach_nested_parts(schema, key, value, read):
    c = load_config(schema, None, [f"{key}={value}"])
    assert isinstance(c, schema) and read(c)
    assert load_config(schema) == schema()  # no file, no override: the defaults


def test_file_then_fields_then_overrides(tmp_path):
    f = tmp_path / "shelf.yaml"
    f.write_text("policy: der3\nhorizon: 5\nablation:\n  foss_choice: true\n")
    c = load_config(ShelfSearchConfig, f, ["horizon=7"], perception="depth")
    assert (c.policy, c.horizon, c.perception, c.ablation.foss_choice) == ("der3", 7, "depth", True)
    f.write_text("object_set: procedural\nablation:\n  sampling: object\n")
    p = load_config(PushStudyConfig, f)
    assert p.object_set == "procedural" and p.ablation.sampling == "object" and p.grasps == 100
    assert hash(p) == hash(PushStudyConfig(**dataclasses.asdict(p)))  # still a frozen value


def test_named_settings_and_records():
    named = {"fast": None}
    with pytest.raises(ConfigError, match="'nothing': no such file or named setting.*fast"):
        load_config(ShelfSearchConfig, "nothing", named=named)
    d = config_dict(ShelfSearchConfig(seed=5))
    assert "seed" not in d and d["ablation"] == {"foss_choice": False, "suction_lift": "over",
                                                 "oracle_push_target": False}


@pytest.mark.parametrize("schema, override, message", [
    (ShelfSearchConfig, "ablation.lift=floor", "ablation.lift=floor"),
    (ShelfSearchConfig, "horizon", "write KEY=VALUE"),
    (ShelfSearchConfig, "policy=xray", "unknown shelf policy 'xray'"),
    (PushStudyConfig, "ablation.sampling=bins", "ablation.sampling 'bins' unknown"),
    (PushStudyConfig, "object_set=toys", "object_set 'toys' unknown"),
    (BinSearchConfig, "heap.layout=pile", "pile"),
])
def test_bad_overrides_are_one_config_error(schema, override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(schema, None, [override])


def test_bad_files_are_named(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("polcy: der3\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        load_config(ShelfSearchConfig, f)


def test_overrides_are_checked_together():
    # The defaults' grasp outcome ("nominal") needs the image planner: switching the planner and
    # the outcome works in either order, and the result alone is checked.
    pairs = ["grasp_planner=indexed", "ablation.grasp_outcome=draw"]
    for order in (pairs, pairs[::-1]):
        c = load_config(BinSearchConfig, None, order)
        assert (c.grasp_planner, c.ablation.grasp_outcome) == ("indexed", "draw")
    with pytest.raises(ConfigError, match="grasp_outcome 'nominal'.*indexed"):
        load_config(BinSearchConfig, None, pairs[:1])
