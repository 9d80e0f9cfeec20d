"""bringup.yaml as plain values, with the line of every key path ("topics[1].codec"), so that every
error about a value names where it was written."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import yaml

from ..errors import ConfigError

_INDEX = re.compile(r"\[\d+\]$")
_MERGE_TAG = "tag:yaml.org,2002:merge"
START_FIX = "start with a bridge: section, as in the README's bringup.yaml walk-through"
MAX_VALUES = 200_000  # values a file holds once its aliases are expanded: far past any fleet's


@dataclass
class Source:
    """Where values came from: the file name, each key path's line, and the source text of
    scalars YAML did not read as strings (for keys that want text)."""

    file: str
    lines: dict[str, int] = field(default_factory=dict)
    texts: dict[str, str] = field(default_factory=dict)
    root_line: int | None = None

    def error(self, key: str, message: str, fix: str | None = None) -> ConfigError:
        line = line_of(self.lines, key) or self.root_line
        return ConfigError(message, file=self.file, line=line, key=key or None, fix=fix)

    def entry_lines(self, path: str) -> dict[str, Any]:
        """An entry's own line and the lines of its keys, relative to it."""
        prefix = path + "."
        lines = {key[len(prefix):]: line for key, line in self.lines.items()
                 if key.startswith(prefix)}
        return {"line": self.lines.get(path, 0), "lines": lines}


def parse(text: str, file: str) -> tuple[Any, Source]:
    src = Source(file)
    loader = None
    try:
        loader = yaml.SafeLoader(text)
        root = loader.get_single_node()
        if root is None:
            raise ConfigError("the file is empty", file=file, fix=START_FIX)
        src.root_line = root.start_mark.line + 1
        data = _Builder(loader, src).build(root, "")
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        problem = exc.problem or exc.context or "invalid YAML"
        column = f" at column {mark.column + 1}" if mark is not None else ""
        raise ConfigError(f"YAML syntax error{column}: {problem}", file=file,
                          line=mark.line + 1 if mark is not None else None,
                          fix="check the indentation (spaces, not tabs) and quote values that "
                              "contain ': ' or ' #' or start with a special character") from None
    except yaml.reader.ReaderError as exc:
        raise ConfigError(f"unacceptable character #x{exc.character:04x} (YAML allows no control "
                          "characters)", file=file, line=text.count("\n", 0, exc.position) + 1,
                          fix="remove the control character") from None
    finally:
        if loader is not None:
            loader.dispose()
    return data, src


class _Builder:
    """Turns the node tree into plain values, recording each key path's line in the Source."""

    def __init__(self, loader: yaml.SafeLoader, src: Source):
        self.loader = loader
        self.src = src
        self.open: set[int] = set()  # collections being built: an alias to one is a cycle
        self.built = 0  # values, each alias expanded: a kilobyte of nested ones means billions

    def build(self, node: yaml.Node, path: str) -> Any:
        self.built += 1
        if self.built > MAX_VALUES:
            raise self.src.error(path, f"the file holds more than {MAX_VALUES} values once its "
                                       "aliases are expanded",
                                 fix="write it out without nested aliases (*name)")
        if isinstance(node, yaml.ScalarNode):
            value = self.loader.construct_object(node)
            if value is not None and not isinstance(value, str):
                self.src.texts[path] = node.value
            return value
        if id(node) in self.open:
            raise self.src.error(path, "an alias refers to the mapping or list that contains it",
                                 fix="remove the recursive alias (*name)")
        self.open.add(id(node))
        try:
            if isinstance(node, yaml.SequenceNode):
                items = []
                for i, item in enumerate(node.value):
                    self.src.lines[f"{path}[{i}]"] = item.start_mark.line + 1
                    items.append(self.build(item, f"{path}[{i}]"))
                return items
            assert isinstance(node, yaml.MappingNode)  # the third kind of node
            return self._mapping(node, path)
        finally:
            self.open.discard(id(node))

    def _mapping(self, node: yaml.MappingNode, path: str) -> dict[str, Any]:
        result: dict[str, Any] = {}
        # "<<: *anchor" merges go in first so that the mapping's own keys override them; of several
        # merged mappings the earlier wins
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                merged = (value_node.value if isinstance(value_node, yaml.SequenceNode)
                          else [value_node])
                for source in reversed(merged):
                    if not isinstance(source, yaml.MappingNode):
                        raise self.src.error(path, "'<<' must be followed by a mapping or a list "
                                                   "of mappings",
                                             fix="merge anchored mappings: <<: *name")
                    result.update(self.build(source, path))
        own: set[str] = set()
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                continue
            if not isinstance(key_node, yaml.ScalarNode):
                raise ConfigError("a key must be a plain name, not a list or mapping",
                                  file=self.src.file, line=key_node.start_mark.line + 1,
                                  key=path or None, fix="write the key as a name followed by ': '")
            key = key_node.value  # the text as written: "yes:" stays "yes", not True
            key_path = join(path, key)
            if key in own:
                raise ConfigError(f"duplicate key '{key}' "
                                  f"(first on line {self.src.lines[key_path]})",
                                  file=self.src.file, line=key_node.start_mark.line + 1,
                                  key=key_path, fix="keep only one of the two")
            own.add(key)
            self.src.lines[key_path] = key_node.start_mark.line + 1
            result[key] = self.build(value_node, key_path)
        return result


def join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _parent(key: str) -> str:
    match = _INDEX.search(key)
    return key[:match.start()] if match else key.rpartition(".")[0]


def line_of(lines: dict[str, int], key: str) -> int | None:
    """The line of dotted key ``key``, or of its nearest parent that was written."""
    while key:
        if key in lines:
            return lines[key]
        key = _parent(key)
    return None

