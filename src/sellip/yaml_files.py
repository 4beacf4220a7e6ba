"""YAML files a user writes (capture.yaml, device.yaml, config files): read with a loader that refuses a key given
twice in one mapping (PyYAML's own safe loader keeps the second value without a word, so a corrected value written
below a stale one would be silently ignored, or the other way round).

- :class:`UniqueKeyLoader` -- ``yaml.SafeLoader`` that raises :class:`DuplicateKeyError` on a repeated key.
- :func:`load_yaml_text`, :func:`load_yaml_file` -- what every reader of a user's YAML file in sellip uses.

Light (PyYAML only): the Snakefile imports it when it parses the workflow.
"""

from __future__ import annotations

from pathlib import Path

import yaml


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A mapping of a YAML document gives the same key twice. ``key`` the key (its path, dotted), ``line`` the
    1-based line of its second occurrence, ``first_line`` of its first."""

    def __init__(self, key: str, line: int, first_line: int):
        self.key, self.line, self.first_line = key, line, first_line
        self.what = (f"given twice (lines {first_line} and {line}); expected each key once (the second value would "
                     "silently replace the first): delete the line that is wrong")
        super().__init__(None, None, f"key '{key}': {self.what}")

    def __str__(self) -> str:
        return self.problem


class UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a key repeated in one mapping (:class:`DuplicateKeyError`, naming the key's
    dotted path and both lines)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            self.flatten_mapping(node)  # merge keys (<<) are not duplicates
            seen: dict = {}
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    hash(key)
                except TypeError:
                    continue  # the base class reports an unhashable key
                if key in seen:
                    raise DuplicateKeyError(_dotted(self, node, key), key_node.start_mark.line + 1, seen[key])
                seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


def _dotted(loader: UniqueKeyLoader, node, key) -> str:
    """``section.key`` where ``node`` is the value of a key of the document's top-level mapping, else ``key``."""
    root = getattr(loader, "_root_node", None)
    if root is not None and root is not node and isinstance(root, yaml.MappingNode):
        for parent_key, value in root.value:
            if value is node:
                return f"{parent_key.value}.{key}"
    return str(key)


def load_yaml_text(text: str):
    """A YAML document as Python objects, a key repeated in one mapping refused (:class:`DuplicateKeyError`; other
    problems are PyYAML's ``yaml.YAMLError``, of which it is one)."""
    loader = UniqueKeyLoader(text)
    try:
        loader._root_node = loader.get_single_node()
        return loader.construct_document(loader._root_node) if loader._root_node is not None else None
    finally:
        loader.dispose()


def load_yaml_file(path: str | Path):
    """:func:`load_yaml_text` of a file (UTF-8)."""
    return load_yaml_text(Path(path).read_text(encoding="utf-8"))
