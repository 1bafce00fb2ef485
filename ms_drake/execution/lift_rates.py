"""A robot station's lift rates in Drake physics per gripper kind and grasp quality, and how well
they predict other attempts beside the quality alone (`ms-drake bench lift-rates`).

The primitive mode's draw lifts a grasp with probability equal to its robust quality (the share of
the contact model's perturbed trials that lift the object). Whether a robot in physics lifts
grasps at those rates is measured here: the lifts and attempts of a station's full-fidelity grasp
attempts (`bench search --fidelity full`, `bench fidelity` records) per gripper kind and quality
level, each level's rate shrunk toward its kind's overall rate with PRIOR_ATTEMPTS pseudo-attempts,
(lifts + k p) / (attempts + k); and, on other attempts, the rates' and the quality's predictions
side by side (share lifted, agreement attempt by attempt, Brier score).
"""

from __future__ import annotations

import gzip
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ms_drake.errors import MsDrakeError

PRIOR_ATTEMPTS = 4.0  # pseudo-attempts at the kind's overall rate added to each quality level


class LiftRateError(MsDrakeError):
    """A lift-rate file or record that cannot be read, with what to do."""


def _level(quality: float) -> float:
    return round(float(quality), 2)


@dataclass
class LiftRates:
    """Lifts and attempts per gripper kind and quality level: counts[kind][level] = [lifts, attempts]."""

    counts: dict = field(default_factory=dict)

    def add(self, kind: str, quality: float, lifted: bool):
        c = self.counts.setdefault(kind, {}).setdefault(_level(quality), [0, 0])
        c[0] += int(bool(lifted))
        c[1] += 1

    def overall(self, kind: str) -> tuple[int, int]:
        """(lifts, attempts) of a gripper kind over all quality levels."""
        levels = self.counts.get(kind, {}).values()
        return sum(c[0] for c in levels), sum(c[1] for c in levels)

    def rate(self, kind: str, quality: float) -> float | None:
        """The probability that a grasp of this kind and quality lifts its object, or None when no
        attempt of the kind was measured."""
        lifts, attempts = self.overall(kind)
        if attempts == 0:
            return None
        p = lifts / attempts
        c = self.counts[kind].get(_level(quality), [0, 0])
        return (c[0] + PRIOR_ATTEMPTS * p) / (c[1] + PRIOR_ATTEMPTS)

    def table(self) -> list[dict]:
        """One row per kind and quality level (and one per kind over all levels, quality None)."""
        rows = []
        for kind in sorted(self.counts):
            for q in sorted(self.counts[kind]):
                lifts, attempts = self.counts[kind][q]
                rows.append({"kind": kind, "quality": q, "lifts": lifts, "attempts": attempts,
                             "rate": self.rate(kind, q)})
            lifts, attempts = self.overall(kind)
            rows.append({"kind": kind, "quality": None, "lifts": lifts, "attempts": attempts,
                         "rate": lifts / attempts})
        return rows


def _open(path: Path):
    return gzip.open(path, "rt") if str(path).endswith(".gz") else open(path)


def read_attempts(files, station: str) -> list[tuple[str, float, bool]]:
    """(gripper kind, quality, lifted) of each of `station`'s full-fidelity grasps in result files
    (.jsonl or .jsonl.gz) of `ms-drake bench search --fidelity full` (every grasp of a search) and
    `ms-drake bench fidelity` (its replayed attempts). Records of another station or fidelity are an
    error."""
    out = []
    for path in map(Path, files):
        if not path.is_file():
            raise LiftRateError(f"{path}: no such file; give result files of `ms-drake bench search --fidelity full` "
                                "or `ms-drake bench fidelity`")
        with _open(path) as f:
            for n, line in enumerate(f, 1):
                if not line.strip():
                    continue
                try:
                    r = json.loads(line)
                except json.JSONDecodeError as e:
                    raise LiftRateError(f"{path}:{n}: not a JSON line ({e.msg})") from None
                if r.get("kind") == "heap" or r.get("error"):
                    continue
                if r.get("kind") == "attempt":  # bench fidelity
                    _check_station(path, n, str(r.get("scenario", "")).split(" of ")[0], station)
                    out.append((r["grasp"], float(r["quality"]), bool(r["full_lifted"])))
                    continue
                if "grasp_qualities" not in r or "fidelity" not in r:
                    raise LiftRateError(f"{path}:{n}: neither a search record with grasp_qualities nor a fidelity "
                                        "attempt; give records of this version's `bench search --fidelity full` "
                                        "or `bench fidelity`")
                if r["fidelity"] != "full":
                    raise LiftRateError(f"{path}:{n}: a {r['fidelity']!r} search; lift rates come from full-fidelity "
                                        "searches (--fidelity full)")
                _check_station(path, n, (r.get("config") or {}).get("scenario", r.get("scenario", "")), station)
                out += [(kind, float(q), bool(ok)) for kind, q, ok in
                        zip(r["grasp_kinds"], r["grasp_qualities"], r["action_successes"]) if kind]  # "": a push
    if not out:
        raise LiftRateError(f"no grasp attempt of {station} in {', '.join(map(str, files))}")
    return out


def count_attempts(files, station: str) -> LiftRates:
    """The LiftRates of `station`'s full-fidelity grasps in result files (read_attempts)."""
    rates = LiftRates()
    for kind, q, ok in read_attempts(files, station):
        rates.add(kind, q, ok)
    return rates


def check_rates(rates: LiftRates, attempts) -> dict:
    """How well the lift rates predict other attempts (kind, quality, lifted) in physics, beside the
    quality alone: the attempts, their share lifted, the mean predicted probability of a lift, and
    the agreement attempt by attempt, expected of a draw and of the likelier outcome (p >= 0.5), and
    the Brier score (mean squared error of the probability; lower is better), for the rates
    ("rates") and for the quality as the probability ("quality")."""
    y = np.array([ok for _, _, ok in attempts], float)
    preds = {"rates": np.array([rates.rate(k, q) if rates.rate(k, q) is not None else q for k, q, _ in attempts]),
             "quality": np.array([q for _, q, _ in attempts])}
    out = {"attempts": len(attempts), "lifted": float(y.mean())}
    for name, p in preds.items():
        out[name] = {"predicted": float(p.mean()), "agreement_draw": float(np.mean(p * y + (1 - p) * (1 - y))),
                     "agreement_likelier": float(np.mean((p >= 0.5) == (y > 0.5))),
                     "brier": float(np.mean((p - y) ** 2))}
    return out


def check_text(c: dict) -> str:
    """check_rates as plain text."""
    lines = [f"held-out attempts: {c['attempts']}, lifted in physics {100 * c['lifted']:.1f} %"]
    for name, label in (("rates", "the lift rates"), ("quality", "the quality")):
        d = c[name]
        lines.append(f"  {label:<15} predict {100 * d['predicted']:.1f} % lifted; agree attempt by attempt "
                     f"{100 * d['agreement_draw']:.1f} % (a draw), {100 * d['agreement_likelier']:.1f} % "
                     f"(the likelier outcome); Brier score {d['brier']:.3f}")
    return "\n".join(lines)


def _check_station(path, n, name: str, station: str):
    if name != station:
        raise LiftRateError(f"{path}:{n}: a record of station {name!r}, not {station!r}; give the records of one "
                            "station (--station)")


def rows_text(rates: LiftRates) -> str:
    """The rates as a plain-text table."""
    out = ["kind          quality  lifted / attempts  rate"]
    for row in rates.table():
        q = "all" if row["quality"] is None else f"{row['quality']:.2f}"
        out.append(f"{row['kind']:<13} {q:>7}  {row['lifts']:>6} / {row['attempts']:<8}  {row['rate']:.2f}")
    return "\n".join(out)
