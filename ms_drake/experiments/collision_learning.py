"""Training and evaluation of SceneCollisionNet (Ch. 6.3.1): `ms-drake train collision`.

A step is one scene of the train shards (ms-drake data collision): its point cloud and query
object are encoded once and all its 2,048 queries classified, the loss mined (10 % hardest + 10 %
random, line 1061); Adam with a cosine schedule; the scenes of an epoch in a seeded random order.
`FILE.ckpt` holds the state a killed run resumes from (experiments.training); the weights file
holds the model, its NetConfig and the run's metadata. Training, evaluation and the bench run the
network on `device` (cpu | cuda | auto; perception.weights.torch_device); the files hold CPU
tensors.

`evaluate_collision` scores a network on the test shards (held-out scenes and objects):
accuracy at P = 0.5, average precision (scikit-learn), and the CPU time per query of the batched
query pass on one thread (the scene and object encoding reported apart, per scene).

`bench_collision` (`ms-drake bench collision`, Table 6.1): one method -- the network or a
point-cloud baseline of ms_drake.collision.baselines -- on held-out scenes made from seeds (test
objects only; cached as npz so every method sees the same scenes): accuracy, AP, CPU time per query.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from sklearn.metrics import average_precision_score

from ms_drake.collision.checker import METHODS, NETWORKS, SceneChecker, default_weights, load_collision_net
from ms_drake.collision.scene_net import NetConfig, make_net, mined_loss
from ms_drake.errors import DatasetError
from ms_drake.experiments.collision_data import load_collision_shards, make_scene
from ms_drake.experiments.training import resume, save_atomically, save_checkpoint, torch_setup
from ms_drake.perception.weights import torch_device


def _tensors(torch, d: dict, i: int, device):
    return (torch.from_numpy(np.asarray(d["scene_points"][i], np.float32)).to(device),
            torch.from_numpy(np.asarray(d["object_points"][i], np.float32)).to(device),
            torch.from_numpy(np.asarray(d["poses"][i], np.float32)).to(device),
            torch.from_numpy(np.asarray(d["labels"][i])).to(device))


ENCODERS = ("point_mlp", "convs", "group_mlp", "object_mlp")  # the per-observation part of the network


def _frozen_encoders(net, encoders) -> None:
    """Copy the scene and object encoders of the weights file `encoders` into `net` and freeze them."""
    src = load_collision_net(encoders, device=net.centres.device)[0]
    for name in ENCODERS:
        try:
            getattr(net, name).load_state_dict(getattr(src, name).state_dict())
        except RuntimeError as e:
            raise DatasetError(f"--encoders {encoders}: its {name} does not fit the network being trained "
                               f"(give the same --voxel-features as the file's, {src.cfg.voxel_features}): {e}") from None
        for q in getattr(net, name).parameters():
            q.requires_grad_(False)


def train_collision(data, out, epochs: int = 20, seed: int = 0, threads: int = 1, lr: float = 1e-3,
                    config: NetConfig = NetConfig(), max_minutes: float = 90.0, hard: float = 0.1,
                    random: float = 0.1, progress=None, command: str = "", encoders=None, device="cpu") -> dict:
    """Train on the train shards of `data`; write `out` (weights + meta) and `out`.ckpt (resume).
    Stops early (after a whole epoch) when `max_minutes` of wall time would be exceeded.
    `encoders`: a weights file whose scene and object encoders are copied and frozen; only the query
    classifier trains (a smaller, faster classifier on a larger network's features), on encodings
    computed once per scene. device: where the network trains (cpu | cuda | auto)."""
    torch = torch_setup(seed, threads)
    dev = torch_device(device)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    ckpt = out.with_suffix(".ckpt")
    d = load_collision_shards(data, "train")
    n = len(d["labels"])
    if n < 1:
        raise DatasetError(f"{data}: no training scenes; write them with `ms-drake data collision`")
    net = make_net(config).to(dev)
    if encoders is not None:
        _frozen_encoders(net, encoders)
    opt = torch.optim.Adam([q for q in net.parameters() if q.requires_grad], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs * n)
    settings = dict(config=asdict(config), epochs=epochs, n=n, lr=lr, hard=hard, random=random,
                    encoders=None if encoders is None else str(encoders))
    cache: dict[int, tuple] = {}  # frozen encoders: scene index -> (voxel features, object features)
    start, history, seconds = resume(torch, ckpt, settings, net, opt, sched)
    t0 = time.perf_counter() - seconds
    gen = torch.Generator().manual_seed(seed)
    for epoch in range(start, epochs):
        te = time.perf_counter()
        if epoch > start and (te - t0) / epoch * (epoch + 1) > 60.0 * max_minutes:
            break
        gen.manual_seed(seed * 100003 + epoch)
        order = np.random.default_rng([seed, epoch]).permutation(n)
        net.train()
        total, right = 0.0, 0.0
        for b, i in enumerate(order):
            scene, obj, poses, labels = _tensors(torch, d, i, dev)
            opt.zero_grad()
            if encoders is None:
                logits = net(scene, obj, poses)
            else:
                if i not in cache:
                    with torch.no_grad():
                        cache[i] = (net.scene_features(scene), net.object_features(obj))
                vox, feat = cache[i]
                logits = net.query(net.first_voxel(vox) + net.first_object(feat), poses)
            loss = mined_loss(logits, labels, hard, random, generator=gen)
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item()
            right += ((logits.detach() > 0) == labels).float().mean().item()
            if progress is not None:
                progress(epoch, b, n, loss.item())
        history.append(dict(epoch=epoch + 1, loss=total / n, train_accuracy=right / n,
                            seconds=time.perf_counter() - te))
        save_checkpoint(torch, ckpt, settings, net, opt, sched, epoch + 1, history, time.perf_counter() - t0)
    meta = dict(data=str(data), encoders=settings["encoders"], train_scenes=n, train_queries=int(d["labels"].size), epochs_done=len(history),
                epochs=epochs, seed=seed, lr=lr, hard=hard, random=random, seconds=time.perf_counter() - t0,
                history=history, command=command, torch=torch.__version__, device=str(dev))
    save_atomically(torch, dict(model=net.state_dict(), config=asdict(config), meta=meta), out)
    return meta


def evaluate_collision(net, data, split: str = "test", max_scenes: int | None = None, threads: int = 1) -> dict:
    """Accuracy, AP and CPU time per query of `net` (on its device) on the `split` shards of `data`
    (module doc)."""
    import torch  # optional heavy dependency

    torch.set_num_threads(threads)
    dev = net.centres.device
    d = load_collision_shards(data, split)
    n = len(d["labels"]) if max_scenes is None else min(max_scenes, len(d["labels"]))
    scores, labels = [], []
    encode_s, query_s = 0.0, 0.0
    with torch.inference_mode():
        for i in range(n):
            scene, obj, poses, lab = _tensors(torch, d, i, dev)
            t = time.process_time()
            code = net.encode(scene, obj)
            t1 = time.process_time()
            logits = net.query(code, poses)
            t2 = time.process_time()
            encode_s += t1 - t
            query_s += t2 - t1
            scores.append(torch.sigmoid(logits).cpu().numpy())
            labels.append(lab.cpu().numpy())
    s, y = np.concatenate(scores), np.concatenate(labels)
    return dict(scenes=n, queries=int(len(y)), positive=float(y.mean()), accuracy=float(((s > 0.5) == y).mean()),
                ap=float(average_precision_score(y, s)) if 0 < y.sum() < len(y) else float("nan"),
                us_per_query=1e6 * query_s / len(y), ms_encode_per_scene=1e3 * encode_s / n)


def bench_scene(seed: int, cache=None, sensor: str = "none") -> dict:
    """Held-out scene `seed` (test objects; collision_data.make_scene), its cloud through the depth
    sensor preset `sensor`, read from / saved to `cache`."""
    name = f"scene_{seed}.npz" if sensor == "none" else f"scene_{seed}_{sensor}.npz"
    path = Path(cache) / name if cache is not None else None
    if path is not None and path.exists():
        return dict(np.load(path))
    s = make_scene(seed, 0, 0, "test", sensor=sensor)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, **s)
        tmp.replace(path)
    return s


def bench_collision(method: str, scenes: int, seed_start: int = 0, cache=None, weights=None, threads: int = 1,
                    progress=None, device: str = "cpu", sensor: str = "none") -> dict:
    """Table 6.1: one method on held-out scenes seed_start.. (module doc); accuracy at 0.5, AP, CPU
    microseconds per query (one thread; the per-scene set-up -- encoding, reconstruction --
    reported apart as ms per scene). device: where the network runs (cpu | cuda | auto); sensor:
    the depth sensor preset of the scene clouds (the same scenes, objects and queries)."""
    if method not in METHODS:
        raise DatasetError(f"collision method {method!r} unknown; choose one of {', '.join(METHODS)}")
    net = None
    if method in NETWORKS:
        import torch  # optional heavy dependency

        torch.set_num_threads(threads)
        weights = weights or default_weights(method)
        net = load_collision_net(weights, method, device)[0]
    scores, labels = [], []
    setup_s = query_s = 0.0
    for k in range(scenes):
        s = bench_scene(seed_start + k, cache, sensor)
        t = time.process_time()
        checker = SceneChecker(method, s["scene_points"], net=net)
        checker.add("query", s["object_points"])
        t1 = time.process_time()
        score = checker.query("query", s["poses"])
        t2 = time.process_time()
        setup_s += t1 - t
        query_s += t2 - t1
        scores.append(score)
        labels.append(np.asarray(s["labels"], bool))
        if progress is not None:
            progress(k)
    sc, y = np.concatenate(scores), np.concatenate(labels)
    return dict(method=method, scenes=scenes, seed_start=seed_start, sensor=sensor, queries=int(len(y)),
                positive=float(y.mean()),
                accuracy=float(((sc > 0.5) == y).mean()),
                ap=float(average_precision_score(y, sc)) if 0 < y.sum() < len(y) else float("nan"),
                us_per_query=1e6 * query_s / len(y), setup_ms_per_scene=1e3 * setup_s / scenes,
                weights=str(weights) if net is not None else None,
                device=str(net.centres.device) if net is not None else None)
