"""A plugin's options: declared once, as a frozen dataclass; checked by the core.

A plugin class declares the table it takes under ``plugins: {NAME: {...}}`` as a nested
``@dataclass(frozen=True) class Options`` whose fields are made with :func:`option`; the core
checks the table with :func:`parse` (every mistake an :class:`rosgate.OptionError` located at the
file's line, worded as for bringup.yaml's own keys) and constructs the plugin with the instance
(``self.options``). Rules that tie fields together go in ``__post_init__``, raising
``OptionError``. Option types: ``str``, ``int``, ``float``, ``bool``, ``Literal[...]``,
``list[T]``, ``dict[str, T]``, ``T | None``, ``Any``. docs/plugins.md ("Options") shows an example
and the errors; a plugin class without ``Options`` takes none.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import MISSING
from enum import Enum
from pathlib import Path
from typing import Any, Literal, Union

from .errors import OptionError

__all__ = ["MISSING", "Declared", "as_options", "check", "declaration_problem", "declared",
           "did_you_mean", "expected", "fields_of", "missing", "option", "parse", "show", "spell",
           "unknown"]


def option(default: Any = MISSING, doc: str = "", *, minimum: float | None = None,
           maximum: float | None = None, choices: typing.Sequence[Any] | None = None,
           above: float | None = None, unit: str = "",
           example: str | None = None, unset: str | None = None, key: str | None = None,
           parse: typing.Callable[..., Any] | None = None, relative: bool = False) -> Any:
    """One option of a plugin's ``Options`` (or one key of bringup.yaml's own schema): its default
    (none: required), a one-line ``doc`` for ``rosgate plugins --options`` and error messages, and
    optionally the range (``minimum``, ``maximum`` inclusive; ``above`` exclusive) or ``choices``.
    ``relative``: a path read relative to the bringup.yaml that gives it (as a cipher's
    ``key_file``), not to the folder rosgate runs in. The rest serves the core's schema: a number's
    ``unit``, an ``example`` for an error's fix, what an absent key means (``unset``, which also
    makes a key without a default optional), the ``key`` path ("reconnect.min") and a ``parse``
    function for a value no type says. List and dict defaults are copied per instance."""
    if not doc:
        raise TypeError("option() needs a doc: one line saying what the option does")
    row = Declared(doc=doc, minimum=minimum, maximum=maximum, above=above, unit=unit,
                   choices=tuple(choices) if choices is not None else None, example=example,
                   unset=unset, key=key or "", parse=parse, relative=relative)
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: type(default)(default),
                                 metadata={"option": row})
    return dataclasses.field(default=default, metadata={"option": row})


@dataclasses.dataclass(frozen=True)
class Declared:
    """One declared option; :func:`fields_of` adds the field's name, type and default."""

    name: str = ""
    type: Any = Any
    default: Any = dataclasses.field(default_factory=lambda: MISSING)  # MISSING: required
    doc: str = ""
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[Any, ...] | None = None
    above: float | None = None
    unit: str = ""
    example: str | None = None
    unset: str | None = None
    key: str = ""  # the path under its table or section: the name, unless option(key=) says
    parse: typing.Callable[..., Any] | None = None
    relative: bool = False  # a path, relative to the bringup.yaml that gives it

    @property
    def required(self) -> bool:
        return self.default is MISSING and self.unset is None

    def fits(self, value: Any) -> bool:
        """Whether ``value`` (of the right type) is finite, within the bounds and the choices."""
        if isinstance(value, float) and not math.isfinite(value):
            return False
        if isinstance(value, (int, float)) and not isinstance(value, bool) and (
                self.minimum is not None and value < self.minimum
                or self.above is not None and value <= self.above
                or self.maximum is not None and value > self.maximum):
            return False
        return self.choices is None or value in self.choices

    def limits(self) -> str:
        """The choices or the range in words ("one of: a, b", "1..9", "> 0, at most 1") or ""."""
        choices = self.choices or _choices(self.type)
        if choices:
            return "one of: " + ", ".join(map(_yaml, choices))
        if self.minimum is not None and self.maximum is not None:
            return f"{_num(self.minimum)}..{_num(self.maximum)}"
        low = (f"> {_num(self.above)}" if self.above is not None
               else f">= {_num(self.minimum)}" if self.minimum is not None else "")
        high = f"at most {_num(self.maximum)}" if self.maximum is not None else ""
        return ", ".join(part for part in (low, high) if part)

    def default_text(self) -> str:
        """The default as bringup.yaml would spell it, or ``required``."""
        if self.unset is not None:
            return self.unset
        return "required" if self.required else _yaml(self.default)

    def fix(self, value: Any = None) -> str:
        """The ``fix:`` of an error about this key: ``value`` or the example as the file would
        have it, or else what the key is and takes."""
        name, value = self.key.rpartition(".")[2] or self.name, value or self.example
        if value:
            return f"e.g. {name}: {value}"
        words, limits = _words(self.type), self.limits()
        details = [words, "" if limits == words else limits,  # a Literal says its choices once
                   "required" if self.required else f"default {self.default_text()}"]
        return f"{name}: {self.doc} ({', '.join(d for d in details if d)})"


def declared(cls: type) -> list[Declared]:
    """The options ``cls`` declares, in declaration order (none without ``Options``)."""
    options = getattr(cls, "Options", None)
    return [] if options is None else fields_of(options)


def fields_of(options: type) -> list[Declared]:
    """A dataclass's fields as options, in order (one not made with :func:`option` has no doc)."""
    hints = typing.get_type_hints(options)
    return [dataclasses.replace(
        row, name=f.name, type=hints[f.name], key=row.key or f.name,
        default=f.default if f.default_factory is MISSING else f.default_factory())
        for f in dataclasses.fields(options) if f.init
        for row in [f.metadata.get("option", Declared())]]


def declaration_problem(cls: type) -> str | None:
    """What is wrong with ``cls.Options`` as a declaration, or ``None``: the registry refuses a
    plugin class whose options could not be parsed (a bug of the plugin, not of a user's file)."""
    options = getattr(cls, "Options", None)
    if options is None:
        return None
    where = f"{cls.__name__}.Options"
    if not (isinstance(options, type) and dataclasses.is_dataclass(options)
            # __dataclass_params__ is what @dataclass sets; typeshed does not declare it
            and options.__dataclass_params__.frozen):  # type: ignore[attr-defined]
        return f"{where} is not a frozen dataclass (decorate it with @dataclass(frozen=True))"
    try:
        rows = declared(cls)
    except Exception as exc:  # an annotation that does not evaluate, a default factory that fails
        return f"{where}: {type(exc).__name__}: {exc}"
    for row in rows:
        unsupported = _unsupported(row.type)
        if unsupported is not None:
            return (f"{where}.{row.name}: the type {spell(unsupported)} is not an option type "
                    "(str, int, float, bool, Literal[...], list[T], dict[str, T], T | None, Any)")
        if not row.required:
            try:
                check(row, row.default)
            except ValueError as exc:
                return f"{where}.{row.name}: its default does not fit: {exc.args[0]}"
    return None


def parse(cls: Any, table: Mapping[str, Any], base_dir: Path | None = None) -> Any:
    """``table`` (a plugin's table under ``plugins:``) checked against ``cls.Options``: the
    ``Options`` instance, or :class:`rosgate.OptionError` naming the key that is wrong and how to
    fix it. A class without ``Options`` takes none: its table must be empty, and it gets ``{}``.
    ``base_dir``: the bringup.yaml's folder, which ``relative`` options' paths are read from."""
    rows = declared(cls)
    name = getattr(cls, "name", cls.__name__)
    by_name = {row.name: row for row in rows}
    for key in table:
        if key not in by_name:
            message, fix = unknown(str(key), list(by_name))
            raise OptionError(str(key), message, fix if rows else
                              f"{name} takes no options: remove it")
    values = {}
    for row in rows:
        if row.name in table:
            try:
                values[row.name] = check(row, table[row.name])
            except ValueError as exc:
                raise OptionError(row.name, *exc.args) from None
            if row.relative and base_dir is not None and isinstance(values[row.name], str):
                values[row.name] = str(base_dir / Path(values[row.name]).expanduser())
        elif row.required:
            raise OptionError(row.name, *missing(row, f"plugins: {name}:"))
    # Options' __post_init__ checks what ties fields together
    return cls.Options(**values) if hasattr(cls, "Options") else {}


def as_options(cls: type, options: Any) -> Any:
    """A plugin's ``self.options``: the ``Options`` the core passes, or a mapping parsed here."""
    return parse(cls, options) if isinstance(options, Mapping) else options


# -- reading a table: a plugin's options and bringup.yaml's own sections alike ------------------

def unknown(key: str, valid: typing.Sequence[str]) -> tuple[str, str]:
    """The message and fix for ``key``, which is not one of ``valid``."""
    return f"unknown key '{key}'{did_you_mean(key, valid)[1]}", f"valid keys are {', '.join(valid)}"


def missing(row: Declared, under: str) -> tuple[str, str]:
    """The message and fix for the required key ``row``, missing from the table ``under``."""
    value = row.example or f"<{_words(row.type)}>"
    where = f" under {under}" if under else ""
    return f"missing required key '{row.key}' ({row.doc})", f"add {row.key}: {value}{where}"


def check(row: Declared, given: Any) -> Any:
    """``given`` as ``row``'s field holds it (an int taken for a float becomes one, a name of an
    Enum's member the member), or ValueError(message, fix)."""
    with contextlib.suppress(_Wrong):
        value = _convert(row.type, given)
        if row.fits(value):
            return value
    choices = row.choices or _choices(row.type)
    close, hint = did_you_mean(str(given), [str(c) for c in choices])
    if choices:
        raise ValueError(f"{show(given)} is not one of {', '.join(map(_yaml, choices))}{hint}",
                         row.fix(close))
    raise ValueError(f"expected {expected(row)}, got {show(given)}", row.fix())


def expected(row: Declared) -> str:
    """What ``row`` takes in words, a number with its unit and bounds: "an integer 1..65535",
    "a number of seconds > 0", "a string or null"."""
    return " or ".join(_number(row, arm) if arm in (int, float) else _words(arm)
                       for arm in _arms(row.type))


def _number(row: Declared, kind: Any) -> str:
    what = f"a number of {row.unit}" if row.unit else _words(kind)
    return " ".join(part for part in (what, row.limits()) if part)


def _num(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


def _arms(hint: Any) -> tuple[Any, ...]:
    return typing.get_args(hint) if typing.get_origin(hint) in (Union, types.UnionType) else (
        hint,)


def _choices(hint: Any) -> tuple[Any, ...]:
    """The values a Literal or an Enum (or a union with one) lists."""
    for arm in _arms(hint):
        if typing.get_origin(arm) is Literal:
            return typing.get_args(arm)
        if isinstance(arm, type) and issubclass(arm, Enum):
            return tuple(member.value for member in arm)
    return ()


class _Wrong(Exception):
    """A value that does not fit a type; the caller words the error."""


def _convert(hint: Any, value: Any) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        for arm in args:
            with contextlib.suppress(_Wrong):
                return _convert(arm, value)
        raise _Wrong
    if origin is Literal or isinstance(hint, type) and issubclass(hint, Enum):
        given = value.value if isinstance(value, Enum) else value
        # type() as well as ==: true is not 1, 1.0 is not 1
        if any(type(given) is type(choice) and given == choice for choice in _choices(hint)):
            return value if origin is Literal else hint(given)
        raise _Wrong
    if origin is list and type(value) is list:
        return [_convert(args[0], item) for item in value]
    if origin is dict and type(value) is dict and all(type(key) is str for key in value):
        return {key: _convert(args[1], item) for key, item in value.items()}
    if hint is float and type(value) is int:
        return float(value)
    # type(), not isinstance(): YAML's true is an int to Python, but not a number to a user
    if hint is Any or hint in (str, int, float, bool, type(None)) and type(value) is hint:
        return value
    raise _Wrong


def _unsupported(hint: Any) -> Any:
    """The part of ``hint`` that is not an option type, or ``None``."""
    if hint in (Any, str, int, float, bool, type(None)):
        return None
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Literal and all(type(a) in (str, int, float, bool) for a in args):
        return None
    if origin in (Union, types.UnionType, list) or origin is dict and args[0] is str:
        parts = args if origin is not dict else args[1:]
        return next((bad for bad in map(_unsupported, parts) if bad is not None), None)
    return hint


# -- words ---------------------------------------------------------------------------------------

_WORDS = {str: "a string", int: "an integer", float: "a number", bool: "true or false",
          type(None): "null", Any: "anything"}


def _words(hint: Any) -> str:
    """A type as a user reads it in an error: ``an integer or null``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        return " or ".join(_words(arm) for arm in args)
    if origin is Literal:
        return "one of: " + ", ".join(_yaml(a) for a in args)
    if origin is list:
        return f"a list ({_words(args[0])} each)"
    if origin is dict:
        return "a mapping" if args[1] is Any else f"a mapping ({_words(args[1])} each)"
    return _WORDS.get(hint, spell(hint))


def spell(hint: Any) -> str:
    """A type as a plugin author writes it: ``int | None``, ``list[str]``; a ``Literal`` as the
    type of its values (its values are listed as choices)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        return " | ".join(spell(arm) for arm in args)
    if origin is Literal:
        return " | ".join(dict.fromkeys(type(a).__name__ for a in args))
    if origin is not None:
        return f"{origin.__name__}[{', '.join(spell(a) for a in args)}]"
    return "None" if hint is type(None) else getattr(hint, "__name__", str(hint))


def _yaml(value: Any) -> str:
    """A value as it is written in bringup.yaml."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, dict)):
        return "[]" if value == [] else "{}" if value == {} else repr(value)
    return str(value)


def show(value: Any) -> str:
    """A value a user wrote, for an error message."""
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        return f"{str(value).lower()} (a boolean)"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return f"a list {value!r}" if len(repr(value)) < 40 else "a list"
    return repr(value)


#: the words one table uses for what another says otherwise: a client's entries name their topic
#: with topic: (service:, action:) and a type with type:, a server's rules with name: and types:
SAME_IDEA = {"topic": ("name",), "service": ("name",), "action": ("name",), "type": ("types",),
             "port": ("ports",), "cipher": ("ciphers",), "types": ("type",), "ports": ("port",),
             "ciphers": ("cipher",), "name": ("topic", "service", "action")}


def did_you_mean(word: str, choices: typing.Sequence[str],
                 cutoff: float = 0.6) -> tuple[str | None, str]:
    """The closest of ``choices`` to ``word`` (or None), and the hint that names it: a word of
    the same idea in another table first, then the closest spelling (``cutoff``: how close, 0 to
    1, as difflib measures)."""
    close = [w for w in SAME_IDEA.get(word, ()) if w in choices] or \
        difflib.get_close_matches(word, choices, n=1, cutoff=cutoff)
    return (close[0], f" (did you mean '{close[0]}'?)") if close else (None, "")
