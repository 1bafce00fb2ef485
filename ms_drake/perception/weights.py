"""Loading the weights file of a learned perception network (`ms-drake train occupancy`, `ms-drake
train segmentation`, `ms-drake train matcher`): a torch checkpoint dict holding 'model' (the state
dict) and 'config' (the network configuration as a dict)."""

from __future__ import annotations

from pathlib import Path

from ms_drake.errors import PerceptionError


def load_network(path: Path | str | None, default_weights, kind: str, data_command: str, build):
    """(network in eval mode, checkpoint dict) from the weights file `path` (None: `default_weights()`)
    written by `ms-drake train <kind>`; `build(config dict) -> network`. A missing file raises
    PerceptionError naming the commands that make it: `ms-drake data <data_command> --out DATA`, then
    the training."""
    import torch  # optional heavy dependency: only the learned backends need it

    p = Path(path) if path is not None else default_weights()
    if not p.is_file():
        raise PerceptionError(f"{kind} weights {p} not found; make them with `ms-drake data {data_command} "
                              f"--out DATA` then `ms-drake train {kind} --data DATA --out {p}`")
    ck = torch.load(p, map_location="cpu", weights_only=False)
    if "model" not in ck or "config" not in ck:
        article = "an" if kind[0] in "aeiou" else "a"
        raise PerceptionError(f"{p} is not {article} {kind} checkpoint (no 'model'/'config'); retrain it with "
                              f"`ms-drake train {kind}`")
    net = build(ck["config"])
    net.load_state_dict(ck["model"])
    net.eval()
    return net, ck
