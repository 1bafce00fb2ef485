"""The device of the learned models (perception.weights.torch_device, the commands' --device): cpu,
auto (cpu on a machine without a GPU, as the tests run) and cuda (one clear error without a GPU);
every loader maps a checkpoint onto the device asked for, and training saves CPU tensors."""

import pytest
import torch

from ms_drake.collision.checker import load_collision_net
from ms_drake.errors import DeviceError, MsDrakeError
from ms_drake.experiments.training import on_cpu, save_atomically
from ms_drake.paths import model_path
from ms_drake.perception.matcher_net import load_matcher
from ms_drake.perception.occupancy_net import load_model as load_occupancy
from ms_drake.perception.segmentation_net import load_model as load_segmentation
from ms_drake.perception.shelf_occupancy_net import load_model as load_shelf_occupancy
from ms_drake.perception.weights import DEVICES, torch_device

NO_GPU = not torch.cuda.is_available()


def test_cpu_and_auto_resolve_to_the_cpu_here():
    assert torch_device("cpu") == torch.device("cpu")
    assert torch_device() == torch.device("cpu")  # the default
    assert torch_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert torch_device(torch.device("cpu")) == torch.device("cpu")


@pytest.mark.skipif(not NO_GPU, reason="this machine has a GPU")
def test_cuda_without_a_gpu_names_the_value_and_the_fix():
    with pytest.raises(DeviceError, match="'cuda'") as e:
        torch_device("cuda")
    assert isinstance(e.value, MsDrakeError)  # the CLI prints it as one line
    assert "--device cpu" in str(e.value) and "--device auto" in str(e.value)


@pytest.mark.parametrize("bad", ["gpu", "CUDA", "cuda:0", "", None])
def test_another_value_lists_the_choices(bad):
    with pytest.raises(DeviceError, match="choose one of cpu, cuda, auto"):
        torch_device(bad)
    assert DEVICES == ("cpu", "cuda", "auto")


LOADERS = [
    (load_segmentation, "segmentation.pt"),
    (load_occupancy, "occupancy.pt"),
    (load_matcher, "matcher.pt"),
    (load_shelf_occupancy, "shelf_occupancy.pt"),
    (lambda path, device: load_collision_net(path, "pointnet_grid", device), "collision_pointnet_grid.pt"),
]


@pytest.mark.parametrize("load, name", LOADERS, ids=[name for _, name in LOADERS])
@pytest.mark.parametrize("device", ["cpu", "auto"])
def test_loaders_map_the_checkpoint_onto_the_device(monkeypatch, load, name, device):
    seen = []
    real = torch.load

    def spy(*args, **kwargs):
        seen.append(kwargs.get("map_location"))
        return real(*args, **kwargs)

    monkeypatch.setattr(torch, "load", spy)
    net = load(model_path(f"weights/{name}"), device=device)[0]
    assert seen == [torch_device(device)]  # map_location: tensors saved anywhere load here
    assert {p.device for p in net.parameters()} == {torch_device(device)}
    assert not net.training


def test_loaders_refuse_cuda_without_a_gpu_before_reading_the_file(tmp_path):
    if not NO_GPU:
        pytest.skip("this machine has a GPU")
    for load, _ in LOADERS:
        with pytest.raises(DeviceError, match="--device cpu"):
            load(tmp_path / "missing.pt", device="cuda")


def test_saved_files_hold_cpu_tensors_and_keep_the_state_dicts_metadata(tmp_path):
    net = torch.nn.BatchNorm1d(3)
    opt = torch.optim.Adam(net.parameters())
    net(torch.randn(4, 3)).sum().backward()
    opt.step()
    obj = dict(model=net.state_dict(), optimizer=opt.state_dict(), meta=dict(history=[1, 2], name="x"))
    moved = on_cpu(torch, obj)
    assert moved["model"]._metadata == net.state_dict()._metadata
    assert moved["meta"] == obj["meta"] and type(moved["optimizer"]["param_groups"]) is list
    save_atomically(torch, obj, tmp_path / "w.pt")
    back = torch.load(tmp_path / "w.pt", map_location="cpu", weights_only=False)
    tensors = [*back["model"].values(), *(t for s in back["optimizer"]["state"].values() for t in s.values())]
    assert tensors and all(t.device.type == "cpu" for t in tensors)
    torch.nn.BatchNorm1d(3).load_state_dict(back["model"])
