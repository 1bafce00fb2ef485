"""What every training entry point shares (`ms-drake train occupancy`, `ms-drake train
shelf-occupancy`): the seeded, deterministic torch set-up, optimizer steps on one fixed batch
(the learned models' overfitting checks), atomic saves, and the checkpoint a
killed run resumes from (`FILE.ckpt` next to the weights; it holds the settings it was made with
and refuses to resume under others). Whatever device a model trains on (the commands' --device,
ms_drake.perception.weights.torch_device), every file is saved with its tensors on the CPU, so
weights and checkpoints load on a machine without a GPU; a checkpoint resumes on any device."""

from __future__ import annotations

import os
from pathlib import Path

from ms_drake.errors import DatasetError


def torch_setup(seed: int, threads: int):
    """torch, seeded, with `threads` intra-op threads and deterministic algorithms."""
    import torch  # optional heavy dependency: only the learned models need it

    torch.manual_seed(seed)
    torch.set_num_threads(max(1, int(threads)))
    torch.use_deterministic_algorithms(True, warn_only=True)
    return torch


def fit_batch(net, opt, loss, steps: int) -> list[float]:
    """`steps` optimizer steps of `net` on `loss()` (a closure over one fixed batch, evaluating `net`);
    the losses before each step."""
    net.train()
    losses = []
    for _ in range(steps):
        opt.zero_grad()
        value = loss()
        value.backward()
        opt.step()
        losses.append(value.item())
    return losses


def on_cpu(torch, obj):
    """`obj` with every tensor in it (in dicts, lists and tuples, e.g. state dicts) moved to the CPU."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        out = type(obj)((k, on_cpu(torch, v)) for k, v in obj.items())
        if hasattr(obj, "_metadata"):  # a module's state dict: its version information
            out._metadata = obj._metadata
        return out
    if type(obj) in (list, tuple):
        return type(obj)(on_cpu(torch, v) for v in obj)
    return obj


def save_atomically(torch, obj, path: Path) -> None:
    """torch.save of `obj` with its tensors on the CPU (`on_cpu`) to a temporary file, then rename:
    an interrupted save never leaves a torn file."""
    path = Path(path)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    torch.save(on_cpu(torch, obj), tmp)
    os.replace(tmp, path)


def resume(torch, ckpt: Path, settings: dict, net, opt, sched) -> tuple[int, list, float]:
    """(first epoch, history, seconds so far) from `ckpt` (model, optimizer and scheduler loaded),
    or (0, [], 0.0) without one; the states go to the device of `net`'s parameters. A checkpoint
    made with other settings raises DatasetError."""
    ckpt = Path(ckpt)
    if not ckpt.exists():
        return 0, [], 0.0
    ck = torch.load(ckpt, map_location="cpu", weights_only=False)
    if ck.get("settings") != settings:
        raise DatasetError(f"{ckpt} was made with other settings ({ck.get('settings')} vs {settings}); delete it "
                           "to start over, or train with the settings it was made with")
    net.load_state_dict(ck["model"])
    opt.load_state_dict(ck["optimizer"])
    sched.load_state_dict(ck["scheduler"])
    return ck["epoch"], ck["history"], ck["seconds"]


def save_checkpoint(torch, ckpt: Path, settings: dict, net, opt, sched, epoch: int, history: list,
                    seconds: float) -> None:
    """The state `resume` reads, after `epoch` epochs and `seconds` of training."""
    save_atomically(torch, dict(settings=settings, model=net.state_dict(), optimizer=opt.state_dict(),
                                scheduler=sched.state_dict(), epoch=epoch, history=history, seconds=seconds), ckpt)
