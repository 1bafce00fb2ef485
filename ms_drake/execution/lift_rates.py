"""A robot station's lift rate per grasp, measured in Drake physics: what the primitive mode draws a
grasp's outcome from when it stands for that robot.

The primitive mode's draw lifts a grasp with probability equal to its robust quality (the share of
the contact model's perturbed trials that lift the object). On a robot in physics the quality
predicts a lift poorly (the compliant pads and the cup hold most grasps of quality 0.25 as well as
of 1.0, and lose some of 1.0 to the heap's load). So when the primitive search stands for a robot
(`BinSearchConfig.reach` names its station), a grasp lifts with that station's measured rate at the
grasp's gripper kind and quality level: the counts of lifts and attempts of the station's
full-fidelity grasp attempts (`diagrams/lift_rates.yaml`, written by `ms-drake bench lift-rates`
from `bench search --fidelity full` and `bench fidelity` records), each level's share shrunk toward
its kind's overall share with PRIOR_ATTEMPTS pseudo-attempts: (lifts + k p) / (attempts + k).
"""

from __future__ import annotations

import datetime
import gzip
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.common.yaml import yaml_load_file

from ms_drake.errors import MsDrakeError
from ms_drake.scenario import default_scenarios_file

PRIOR_ATTEMPTS = 4.0  # pseudo-attempts at the kind's overall rate added to each quality level


class LiftRateError(MsDrakeError):
    """A lift-rate file or record that cannot be read, with what to do."""


def default_lift_rates_file() -> Path:
    """The shipped lift rates: diagrams/lift_rates.yaml beside the scenario file."""
    return default_scenarios_file().parent / "lift_rates.yaml"


def _level(quality: float) -> float:
    return round(float(quality), 2)


@dataclass
class LiftRates:
    """Lifts and attempts per gripper kind and quality level: counts[kind][level] = [lifts, attempts]."""

    counts: dict = field(default_factory=dict)
    source: str = ""

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

    def to_yaml(self, station: str) -> str:
        lines = [f"{station}:", f"  source: {json.dumps(self.source)}"]
        for kind in sorted(self.counts):
            lines.append(f"  {kind}:")
            for q in sorted(self.counts[kind]):
                lifts, attempts = self.counts[kind][q]
                lines.append(f"    - {{quality: {q}, lifts: {lifts}, attempts: {attempts}}}")
        return "\n".join(lines) + "\n"


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
    the agreement attempt by attempt, expected of a draw and of the likelier outcome (p >= 0.5),
    for the rates ("rates") and for the quality as the probability ("quality")."""
    y = np.array([ok for _, _, ok in attempts], float)
    preds = {"rates": np.array([rates.rate(k, q) if rates.rate(k, q) is not None else q for k, q, _ in attempts]),
             "quality": np.array([q for _, q, _ in attempts])}
    out = {"attempts": len(attempts), "lifted": float(y.mean())}
    for name, p in preds.items():
        out[name] = {"predicted": float(p.mean()), "agreement_draw": float(np.mean(p * y + (1 - p) * (1 - y))),
                     "agreement_likelier": float(np.mean((p >= 0.5) == (y > 0.5)))}
    return out


def check_text(c: dict) -> str:
    """check_rates as plain text."""
    lines = [f"held-out attempts: {c['attempts']}, lifted in physics {100 * c['lifted']:.1f} %"]
    for name, label in (("rates", "the lift rates"), ("quality", "the quality")):
        d = c[name]
        lines.append(f"  {label:<15} predict {100 * d['predicted']:.1f} % lifted; agree attempt by attempt "
                     f"{100 * d['agreement_draw']:.1f} % (a draw), {100 * d['agreement_likelier']:.1f} % "
                     "(the likelier outcome)")
    return "\n".join(lines)


def _check_station(path, n, name: str, station: str):
    if name != station:
        raise LiftRateError(f"{path}:{n}: a record of station {name!r}, not {station!r}; give the records of one "
                            "station (--station)")


def load_lift_rates(station: str, path=None) -> LiftRates | None:
    """The measured lift rates of `station` in `path` (default: the shipped diagrams/lift_rates.yaml),
    or None when the file holds none for it."""
    path = Path(path) if path is not None else default_lift_rates_file()
    if not path.is_file():
        if path == default_lift_rates_file():
            return None
        raise LiftRateError(f"{path}: no such lift-rate file")
    try:
        data = yaml_load_file(str(path)) or {}
    except RuntimeError as e:
        raise LiftRateError(f"{path}: {str(e).splitlines()[0]}") from None
    entry = data.get(station)
    if entry is None:
        return None
    rates = LiftRates(source=str(entry.get("source", "")))
    for kind, rows in entry.items():
        if kind == "source":
            continue
        for row in rows:
            try:
                rates.counts.setdefault(kind, {})[_level(row["quality"])] = [int(row["lifts"]), int(row["attempts"])]
            except (KeyError, TypeError, ValueError):
                raise LiftRateError(f"{path}: {station}.{kind}: a row {row!r}; write "
                                    "{quality: Q, lifts: L, attempts: A}") from None
    return rates


def write_lift_rates(path, station: str, rates: LiftRates):
    """Write (or replace) `station`'s entry of a lift-rate file, keeping the other stations'."""
    path = Path(path)
    entries = {}
    if path.is_file():
        data = yaml_load_file(str(path)) or {}
        for name in data:
            if name != station:
                entries[name] = load_lift_rates(name, path).to_yaml(name)
    entries[station] = rates.to_yaml(station)
    header = ("# Lift rates of the robot stations' grasps in Drake physics (ms_drake.execution.lift_rates):\n"
              "# the primitive search that stands for a station (reach=<station>) draws a grasp's outcome\n"
              "# from them. Written by `ms-drake bench lift-rates`.\n")
    path.write_text(header + "\n".join(entries[k] for k in sorted(entries)))


def describe_source(files, command: str) -> str:
    """A lift-rate entry's provenance: the command, the records' names and the date."""
    names = ", ".join(Path(f).name for f in files)
    return f"{command} ({names}), {datetime.date.today().isoformat()}"


def rows_text(rates: LiftRates) -> str:
    """The rates as a plain-text table."""
    out = ["kind          quality  lifted / attempts  rate"]
    for row in rates.table():
        q = "all" if row["quality"] is None else f"{row['quality']:.2f}"
        out.append(f"{row['kind']:<13} {q:>7}  {row['lifts']:>6} / {row['attempts']:<8}  {row['rate']:.2f}")
    return "\n".join(out)
