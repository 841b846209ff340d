"""Duplicate keys in a JSON document: an error naming the key, not the last value silently
kept.

``json.loads`` (and so FastAPI and pydantic) keeps the last of two equal keys in an object: a
request with ``"t"`` twice in a plot, or a job with a track name twice under ``tracks``, was
answered as if the earlier value (a whole track) had never been sent; a sensor file with a
radar's ``range_error_m`` twice used the second (the service answers 422, the sensor file's
reader an :class:`solver.InputError`).
"""

from __future__ import annotations

import json
from typing import Any

TWICE = "is given twice in one JSON object: give each key once (a JSON parser keeps only one)"


class _Duplicated(dict):  # type: ignore[type-arg]
    """An object that had a key twice (:attr:`key`: the first repeated one)."""

    key: str


def duplicate_key(body: bytes | str) -> tuple[str | int, ...] | None:
    """The location (``("plots", 3, "t")``) of a key that appears twice in one object of the
    JSON ``body`` (the outermost such object's, then in document order), or None (also for a
    body that is not JSON: its own error says so). Searched only when some object had one."""
    found = False

    def pairs(items: list[tuple[str, Any]]) -> dict[str, Any]:
        nonlocal found
        out = dict(items)
        if len(out) == len(items):
            return out
        found = True
        dup = _Duplicated(items)
        seen: set[str] = set()
        for k, _ in items:
            if k in seen:
                dup.key = k
                break
            seen.add(k)
        return dup

    try:
        doc = json.loads(body, object_pairs_hook=pairs)
    except (ValueError, RecursionError):
        return None
    if not found:
        return None
    stack: list[tuple[Any, tuple[str | int, ...]]] = [(doc, ())]
    while stack:  # depth-first in document order, without recursion (any nesting depth)
        node, loc = stack.pop()
        if isinstance(node, _Duplicated):
            return (*loc, node.key)
        if isinstance(node, dict):
            stack.extend(((v, (*loc, k)) for k, v in reversed(node.items())))
        elif isinstance(node, list):
            stack.extend(((v, (*loc, i)) for i, v in reversed(list(enumerate(node)))))
    return None
