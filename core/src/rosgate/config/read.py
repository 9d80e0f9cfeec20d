"""A section of bringup.yaml read against its declaration: a dataclass whose fields are made with
:func:`rosgate.option`. Unknown keys (with the closest valid one), missing required keys, and each
value by its declared kind, every error located at its key."""

from __future__ import annotations

from functools import cache
from typing import Any

from ..options import Declared, did_you_mean, fields_of
from . import kinds
from .kinds import Key
from .source import Source, join


@cache
def keys(section: type) -> tuple[Declared, ...]:
    """The keys ``section`` declares, in the order the file's reference lists them."""
    return tuple(row for row in fields_of(section) if row.doc)


def names(section: type, under: str = "") -> tuple[str, ...]:
    """The valid keys of ``section`` (or of its sub-mapping ``under``: "reconnect")."""
    prefix = f"{under}." if under else ""
    found = [row.key[len(prefix):].partition(".")[0] for row in keys(section)
             if row.key.startswith(prefix)]
    return tuple(dict.fromkeys(found))


def example(section: type, under: str) -> str:
    """A sub-mapping as a fix writes it: its first three keys with their examples."""
    rows = [row for row in keys(section) if row.key.startswith(under + ".")][:3]
    return "{" + ", ".join(f"{row.key.rpartition('.')[2]}: {row.example}" for row in rows) + "}"


def read(src: Source, data: Any, path: str, section: type) -> dict[str, Any]:
    """The keys of ``data`` (the mapping at ``path``) that were written, each as its field holds
    it, by field name; the dataclass's defaults stand for the others."""
    check_keys(src, data, path, names(section))
    require(src, data, path, section)
    values: dict[str, Any] = {}
    checked = set()
    for row in keys(section):
        under, _, name = row.key.rpartition(".")
        mapping = data
        if under:
            given = data.get(under)
            if given is None:  # absent or written empty
                continue
            row_path = join(path, under)
            if not isinstance(given, dict):
                parent = Declared(under, dict, None, example=example(section, under), key=under)
                kinds.mapping(Key(src, path, parent), given)
            if under not in checked:
                check_keys(src, given, row_path, names(section, under))
                checked.add(under)
            mapping = given
        if name in mapping:
            key = Key(src, join(path, under) if under else path, row)
            values[row.name] = (row.parse or kinds.plain)(key, mapping[name])
    return values


def check_keys(src: Source, data: dict, path: str, valid: tuple[str, ...]) -> None:
    for key in data:
        if key not in valid:
            hint = did_you_mean(key, valid)[1]
            raise src.error(join(path, key), f"unknown key '{key}'{hint}",
                            fix=f"valid keys are {', '.join(valid)}")


def require(src: Source, data: dict, path: str, section: type) -> None:
    for row in keys(section):
        if row.required and row.key not in data:
            where = f" under {path}:" if path else ""
            raise src.error(join(path, row.key), f"missing required key '{row.key}'",
                            fix=f"add {row.key}: {row.example}{where}")
