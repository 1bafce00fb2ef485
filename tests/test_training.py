"""ms_drake.experiments.training: a checkpoint round trip resumes the same state; other settings
are refused with a DatasetError naming the file."""

import pytest

from ms_drake.errors import DatasetError
from ms_drake.experiments.training import resume, save_checkpoint, torch_setup


def _parts(torch):
    net = torch.nn.Linear(3, 2)
    opt = torch.optim.SGD(net.parameters(), lr=0.1)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=1)
    return net, opt, sched


def test_checkpoint_round_trip_and_refusal(tmp_path):
    torch = torch_setup(0, 1)
    ckpt = tmp_path / "w.ckpt"
    net, opt, sched = _parts(torch)
    assert resume(torch, ckpt, {"a": 1}, net, opt, sched) == (0, [], 0.0)  # no checkpoint yet
    net(torch.ones(1, 3)).sum().backward()
    opt.step()
    sched.step()
    save_checkpoint(torch, ckpt, {"a": 1}, net, opt, sched, 3, [{"epoch": 3}], 12.5)
    assert not list(tmp_path.glob("*.tmp"))  # written atomically
    net2, opt2, sched2 = _parts(torch_setup(1, 1))  # other initial weights
    assert resume(torch, ckpt, {"a": 1}, net2, opt2, sched2) == (3, [{"epoch": 3}], 12.5)
    assert torch.equal(net2.weight, net.weight) and sched2.last_epoch == sched.last_epoch
    with pytest.raises(DatasetError, match="w.ckpt was made with other settings"):
        resume(torch, ckpt, {"a": 2}, *_parts(torch))
