"""Which valve a recording belongs to: a mapping given by the user, else a `tag`
column in the file, else the file name up to its last `_` or `-`.

Shared by the valve trend (`jaxstiction trend`) and the screen's per-valve summary
(`screen --by-valve`). Host-side, no JAX.
"""

from __future__ import annotations

import csv
import json
import re
from collections.abc import Mapping
from pathlib import Path

from .._checks import LoopDataError, one_line


def read_tags(path) -> dict[str, str]:
    """A mapping recording name → valve tag from `path`: a JSON object `{name: tag}`,
    or a `labels.json` whose `loops` give each name a `valve`; or a CSV file with
    `name` and `tag` (or `valve`) columns.

    **Raises:** a one-line `LoopDataError` when the file cannot be read or has no
    such mapping."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise LoopDataError(f"{path}: cannot read the tags file ({e.strerror or e})") from e
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except ValueError as e:
            raise LoopDataError(f"{path}: not JSON ({one_line(e)})") from e
        if isinstance(data, dict) and isinstance(data.get("loops"), dict):
            out = {str(k): str(v["valve"]) for k, v in data["loops"].items() if isinstance(v, dict) and "valve" in v}
        elif isinstance(data, dict):
            out = {str(k): str(v) for k, v in data.items() if isinstance(v, (str, int, float))}
        else:
            out = {}
    else:
        rows = list(csv.DictReader(text.splitlines()))
        cols = {c.strip().lower(): c for c in (rows[0] if rows else {}) if c}
        name, tag = cols.get("name"), cols.get("tag") or cols.get("valve")
        if name is None or tag is None:
            raise LoopDataError(f"{path}: the tags file needs `name` and `tag` columns")
        out = {str(r[name]).strip(): str(r[tag]).strip() for r in rows}
    if not out:
        raise LoopDataError(f"{path}: no recording name -> tag mapping found")
    return out


def tag_column(path: Path):
    """The first value of a `tag` column of a CSV file, or `None`."""
    if path.suffix.lower() != ".csv":
        return None
    try:
        with open(path, newline="") as f:
            head = f.readline()
            delim = max(",;\t", key=head.count)
            cols = [c.strip().lower() for c in head.strip().split(delim)]
            if "tag" not in cols:
                return None
            row = next(csv.reader(f, delimiter=delim), None)
    except OSError:
        return None
    return row[cols.index("tag")].strip() if row and len(row) > cols.index("tag") else None


def default_tag(name: str) -> str:
    """The tag of a recording named `name` with no mapping nor `tag` column: the name
    up to its last `_` or `-` (the name itself when it has neither)."""
    m = re.match(r"^(.+)[_-][^_-]+$", name)
    return m.group(1) if m else name


def natural_key(s: str):
    """A sort key that orders the digits in `s` as numbers (`L9` before `L10`)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


def tag_of(name: str, path, mapping: Mapping[str, str] | None = None) -> str:
    """The valve tag of the recording `name` read from `path`: `mapping`'s entry for
    the name or the file's stem, else the file's `tag` column, else `default_tag`."""
    path = Path(path)
    mapping = mapping or {}
    return mapping.get(name) or mapping.get(path.stem) or tag_column(path) or default_tag(name)
