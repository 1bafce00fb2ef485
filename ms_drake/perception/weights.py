"""The torch device a learned model runs on (`torch_device`: cpu | cuda | auto, the `--device` of
the train and bench commands), and loading the weights file of a learned perception network
(`ms-drake train occupancy`, `ms-drake train segmentation`, `ms-drake train matcher`): a torch
checkpoint dict holding 'model' (the state dict) and 'config' (the network configuration as a
dict)."""

from __future__ import annotations

from pathlib import Path

from ms_drake.errors import DeviceError, PerceptionError

#: The values of `torch_device` (and of the commands' --device).
DEVICES = ("cpu", "cuda", "auto")


def torch_device(name="cpu"):
    """The torch.device of `name`: "cpu"; "cuda" (the current GPU; DeviceError on a machine without
    one); "auto" (cuda where torch finds a GPU, else cpu). A torch.device is returned as given."""
    import torch  # optional heavy dependency: only the learned models need it

    if isinstance(name, torch.device):
        return name
    if name not in DEVICES:
        raise DeviceError(f"device {name!r} unknown; choose one of {', '.join(DEVICES)}")
    if name == "cuda" and not torch.cuda.is_available():
        raise DeviceError("device 'cuda': torch finds no CUDA device on this machine; use --device cpu, or "
                          "--device auto (a GPU where one exists, else the CPU)")
    return torch.device("cuda" if name != "cpu" and torch.cuda.is_available() else "cpu")


def load_network(path: Path | str | None, default_weights, kind: str, data_command: str, build, device="cpu"):
    """(network in eval mode on `device` (torch_device), checkpoint dict) from the weights file `path`
    (None: `default_weights()`) written by `ms-drake train <kind>`; `build(config dict) -> network`.
    A missing file raises PerceptionError naming the commands that make it: `ms-drake data
    <data_command> --out DATA`, then the training."""
    import torch  # optional heavy dependency: only the learned backends need it

    dev = torch_device(device)
    p = Path(path) if path is not None else default_weights()
    if not p.is_file():
        raise PerceptionError(f"{kind} weights {p} not found; make them with `ms-drake data {data_command} "
                              f"--out DATA` then `ms-drake train {kind} --data DATA --out {p}`"
                              + (" --overwrite-shipped" if path is None else ""))
    retrain = f"give a weights file written by `ms-drake train {kind}`, or retrain it with `ms-drake train {kind}`"
    try:
        ck = torch.load(p, map_location=dev, weights_only=False)
    except Exception as e:  # garbage bytes, a truncated file: torch / pickle raise many types
        raise PerceptionError(f"{kind} weights {p} cannot be read ({type(e).__name__}: "
                              f"{str(e).splitlines()[0] if str(e) else 'unreadable'}); {retrain}") from None
    if not isinstance(ck, dict) or "model" not in ck or "config" not in ck:
        article = "an" if kind[0] in "aeiou" else "a"
        raise PerceptionError(f"{p} is not {article} {kind} checkpoint (no 'model'/'config'); {retrain}")
    try:
        net = build(ck["config"]).to(dev)
        net.load_state_dict(ck["model"])
    except Exception as e:  # another network's file: unknown config keys, missing / mis-shaped tensors
        raise PerceptionError(f"{p} does not hold the {kind} network ({type(e).__name__}: "
                              f"{str(e).splitlines()[0] if str(e) else 'mismatch'}); {retrain}") from None
    net.eval()
    return net, ck
