"""Column matching shared by the CSV and the `.mat` readers: which keys of a file or
a struct are `OP`, `PV`, `SP` and `t`, tagged historian columns
(`FIC101.OP`, ...), and the short names that errors quote."""

from __future__ import annotations

from collections.abc import Iterable

from .._checks import LoopDataError, one_line


_COLUMN = {"op": "OP", "pv": "PV", "sp": "SP", "t": "t"}


# ------------------------------------------------------------------------- helpers


def _norm(key: object) -> str:
    return "".join(str(key).split()).lower()


def _short(text: object, limit: int = 30) -> str:
    s = one_line(text)
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _found(keys: Iterable[object], limit: int = 12) -> str:
    keys = [_short(k) for k in keys]
    shown = ", ".join(keys[:limit])
    if len(keys) > limit:
        shown += f", ... ({len(keys) - limit} more)"
    return shown or "none"


_TIME_NAMES = ("t", "time", "timestamp", "datetime")
_TAG_SEPARATORS = (".", "_", "/", ":", "-", " ", "\t")


def _tag_split(key: object) -> tuple[str, str] | None:
    """`(prefix, "op"|"pv"|"sp")` for a historian-style column name such as
    `FIC101.PV`, `FIC101_OP` or `FIC101 SP` (the part after the last separator),
    else `None`."""
    text = str(key).strip()
    i = max(text.rfind(c) for c in _TAG_SEPARATORS)
    prefix, suffix = text[:i].strip(), text[i + 1 :].strip().lower()
    return (prefix, suffix) if i > 0 and prefix and suffix in ("op", "pv", "sp") else None


def _tagged_loops(keys: Iterable[object], where: str) -> dict[str, dict[str, object]]:
    """The loops of a file whose columns are tagged (`FIC101.OP`, `FIC101.PV`, ...):
    tag prefix → `{"op": key, "pv": key[, "sp": key]}`, for prefixes with both OP
    and PV. Prefixes match case-insensitively."""
    groups: dict[str, dict[str, object]] = {}
    for key in keys:
        tag = _tag_split(key)
        if tag is None:
            continue
        prefix, canon = tag
        g = groups.setdefault(prefix.lower(), {"": prefix})
        if canon in g:
            raise LoopDataError(f"ambiguous columns {_short(g[canon])!r} and {_short(key)!r} in {where} "
                                f"(both read as `{_COLUMN[canon]}` of {prefix!r})")
        g[canon] = key
    return {str(g.pop("")): g for g in groups.values() if "op" in g and "pv" in g}


def _match_columns(keys: Iterable[object], where: str, name: str | None = None) -> dict[str, object]:
    """Map the canonical names `op, pv, sp, t` to the original keys present in `keys`.

    Matching is case-insensitive after stripping spaces; `time`, `timestamp` and
    `datetime` are accepted for `t`. Without columns named `OP` and `PV`, tagged
    columns (`FIC101.OP`, `FIC101.PV`, optionally `FIC101.SP`; separators `.`, `_`,
    `/`, `:`, `-` or a space) are read: the one tag that has both, or the tag `name`
    when several do.
    Raises when `OP` or `PV` is missing, a name matches twice, or several tagged
    loops are present and `name` picks none of them.
    """
    keys = list(keys)
    aliases = {"op": "op", "pv": "pv", "sp": "sp", **{k: "t" for k in _TIME_NAMES}}
    out: dict[str, object] = {}
    for key in keys:
        canon = aliases.get(_norm(key))
        if canon is None:
            continue
        if canon in out:
            raise LoopDataError(
                f"ambiguous columns {_short(out[canon])!r} and {_short(key)!r} "
                f"in {where} (both read as `{_COLUMN[canon]}`)"
            )
        out[canon] = key
    if "op" in out and "pv" in out:
        return out
    loops = _tagged_loops(keys, where)
    if loops:
        by_key = {k.lower(): k for k in loops}
        tag = by_key.get(name.strip().lower()) if name is not None else None
        if tag is None and len(loops) == 1:
            tag = next(iter(loops))
        if tag is None:
            what = f"no loop named {name!r}" if name is not None else f"{len(loops)} loops"
            raise LoopDataError(f"{what} in {where} (tags with OP and PV columns: {_found(loops, limit=20)}); "
                                "pick one with `name` (--name on the command line)")
        return {**{k: v for k, v in out.items() if k == "t"}, **loops[tag]}
    for canon in ("op", "pv"):
        if canon not in out:
            raise LoopDataError(
                f"`{canon.upper()}` column missing in {where} (found: {_found(keys)})"
            )
    return out
