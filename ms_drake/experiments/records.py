"""Reading the JSON-lines record files the benchmarks write (one JSON object per line).

Every reader of a result file goes through `read_record_file`: the benchmarks when they resume,
and the tables, plots and replays that read finished files. A run killed mid-write leaves a torn
last line (no newline at its end); that line is skipped (and, when resuming, cut from the file so
the next record starts on a line of its own). Any other line that is not a JSON object, or a
record without a field the reader needs, is an error naming the file and the line.
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

from ms_drake.errors import RecordFileError

#: The fields the tables, plots and replays need in every record of each command's result files.
RECORD_FIELDS = {
    "bench search": ("seed", "policy", "objects", "success", "actions", "config"),
    "bench push": ("seed", "policy", "separation_gain", "jaw_gain", "suction_gain", "overall_gain", "pushed"),
    "bench shelf": ("seed", "policy", "occluders", "success", "steps", "actions"),
    "bench shelf-physics": ("seed", "policy", "occluders", "success", "steps"),
    "bench rearrange": ("seed", "method"),
}


def read_record_file(path, required=("seed",), writer: str = "", resume: bool = False) -> list[dict]:
    """The records of the JSON-lines file `path` (gzipped when it ends in .gz, as the records kept
    in the repository are), in file order.

    required: fields every record must have. writer: the command that writes such files (e.g.
    "bench search"), named in the errors. resume: reading a file a benchmark is about to append to:
    a missing or empty file is no records and a torn last line is cut from the file; otherwise a
    missing file or one without records raises RecordFileError."""
    path = Path(path)
    how = f"; make it with `ms-drake {writer} ... --out {path}`" if writer else ""
    if not path.exists():
        if resume:
            return []
        raise RecordFileError(f"{path}: no such result file{how}")
    if path.is_dir():
        raise RecordFileError(f"{path} is a folder; give a result .jsonl file{how.replace('make it', 'made')}")
    packed = path.suffix == ".gz"  # the records kept in the repository are compressed
    try:
        text = gzip.decompress(path.read_bytes()).decode() if packed else path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise RecordFileError(f"{path}: not a JSON-lines result file ({e}); give a .jsonl (or gzipped "
                              f".jsonl.gz) file{how}") from None
    lines = text.split("\n")  # a file that ends with a newline gives a last empty piece
    torn = False
    recs = []
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
            if not isinstance(rec, dict):
                raise ValueError(f"a JSON {type(rec).__name__}, not an object")
        except ValueError as e:
            if n == len(lines):  # no newline after it: a run killed while writing it
                torn = True
                continue
            raise RecordFileError(f"{path}, line {n}: not a JSON record ({e}); delete or repair that line "
                                  "(the rest of the file is kept)") from None
        missing = [k for k in required if k not in rec]
        if not missing and "seed" in required and not _is_int(rec["seed"]):
            raise RecordFileError(f"{path}, line {n}: seed {rec['seed']!r} is not an integer; give a result file "
                                  f"of `ms-drake {writer or '...'}`, or delete that line")
        if missing:
            raise RecordFileError(f"{path}, line {n}: the record has no {', '.join(map(repr, missing))}; "
                                  f"give a result file of `ms-drake {writer or '...'}`, or delete that line")
        recs.append(rec)
    if torn and resume and not packed:
        kept = text[:text.rfind("\n") + 1]
        path.write_text(kept)
    if not recs and not resume:
        raise RecordFileError(f"{path}: no records in the file{how}")
    return recs


def _is_int(value) -> bool:
    try:
        return int(value) == float(value)
    except (TypeError, ValueError):
        return False
