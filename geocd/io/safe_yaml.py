"""A bounded, strict YAML (and JSON) reader for the files users hand to geocd.

``yaml.safe_load`` expands anchors and aliases lazily: a 1.5 KB "billion laughs" document parses in
microseconds into a graph whose expanded size is 10⁹ nodes, and the first ``repr()`` or walk of it takes
minutes and gigabytes. It also keeps the last of two equal keys without a word. :func:`load_yaml` refuses
both: at most :data:`MAX_ALIASES` aliases, at most :data:`MAX_EXPANDED_NODES` nodes once aliases are
expanded, no recursive anchors, no duplicate keys (the message names the key and both lines).
:func:`load_json` refuses duplicate keys too.
"""

from __future__ import annotations

import json
from typing import Any

import yaml

__all__ = ["load_yaml", "load_json", "YAMLLimitError", "MAX_ALIASES", "MAX_EXPANDED_NODES"]

#: aliases (``*name``) a document may use; geocd's own files use none
MAX_ALIASES = 100
#: nodes of the document once every alias is expanded (a manifest of 1000 images has ~10⁴)
MAX_EXPANDED_NODES = 200_000


class YAMLLimitError(yaml.YAMLError, ValueError):
    """A document is refused before it is built: too many aliases, too large expanded, or a duplicate key."""


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that counts aliases and refuses duplicate mapping keys."""

    def __init__(self, stream: Any) -> None:
        super().__init__(stream)
        self._aliases = 0

    def compose_node(self, parent, index):  # type: ignore[override]
        if self.check_event(yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > MAX_ALIASES:
                mark = self.peek_event().start_mark
                raise YAMLLimitError(
                    f"more than {MAX_ALIASES} YAML aliases (*name), line {mark.line + 1}; write the values out "
                    "instead of repeating anchors"
                )
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):  # type: ignore[override]
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.get(key)
                except TypeError:  # an unhashable key: SafeConstructor names it
                    continue
                line = key_node.start_mark.line + 1
                if first is not None:
                    raise YAMLLimitError(
                        f"duplicate key {_short(key)} at line {line} (first at line {first}); keep one of them "
                        "(YAML would silently keep only the last)"
                    )
                seen[key] = line
        return super().construct_mapping(node, deep=deep)


def _short(v: Any, n: int = 60) -> str:
    s = repr(v) if isinstance(v, (str, int, float, bool)) or v is None else f"<{type(v).__name__}>"
    return s if len(s) <= n else s[: n - 3] + "..."


def _expanded_size(root: yaml.Node) -> int:
    """Nodes of the document with every alias expanded (shared nodes counted each time they are used);
    stops counting past :data:`MAX_EXPANDED_NODES`. Raises YAMLLimitError on a recursive anchor."""
    memo: dict[int, int] = {}
    active: set[int] = set()

    def size(node: yaml.Node) -> int:
        k = id(node)
        if k in memo:
            return memo[k]
        if k in active:
            raise YAMLLimitError(
                f"a recursive YAML anchor (line {node.start_mark.line + 1}) refers to itself; remove the alias"
            )
        if isinstance(node, yaml.ScalarNode):
            return 1
        active.add(k)
        total = 1
        children = node.value if isinstance(node, yaml.SequenceNode) else [c for kv in node.value for c in kv]
        for c in children:
            total += size(c)
            if total > MAX_EXPANDED_NODES:
                break
        active.discard(k)
        memo[k] = min(total, MAX_EXPANDED_NODES + 1)
        return memo[k]

    return size(root)


def load_yaml(text: str) -> Any:
    """Parse one YAML document with the limits of this module.

    Raises
    ------
    yaml.YAMLError
        Syntax errors; :class:`YAMLLimitError` (a ``yaml.YAMLError``) for too many aliases, an expanded size
        over :data:`MAX_EXPANDED_NODES` nodes, a recursive anchor or a duplicate key.
    """
    loader = _StrictLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if loader._aliases:
            n = _expanded_size(node)
            if n > MAX_EXPANDED_NODES:
                raise YAMLLimitError(
                    f"its aliases expand to more than {MAX_EXPANDED_NODES} values (a 'billion laughs' document?); "
                    "write the values out instead of nesting anchors"
                )
        return loader.construct_document(node)
    finally:
        loader.dispose()


def load_json(text: str) -> Any:
    """``json.loads`` that refuses duplicate keys (:class:`YAMLLimitError`, a ``ValueError``)."""

    def pairs(items: list[tuple[str, Any]]) -> dict:
        out: dict = {}
        for k, v in items:
            if k in out:
                raise YAMLLimitError(f"duplicate key {_short(k)}; keep one of them (JSON readers keep only the last)")
            out[k] = v
        return out

    return json.loads(text, object_pairs_hook=pairs)
