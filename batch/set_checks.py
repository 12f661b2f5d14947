"""Checks of a set file's tables and values, shared by the set file's parser (:mod:`batch.setfile`) and its
``[scenes.randomize]`` tables (:mod:`batch.randomize`).

``ctx`` is the parser's context: ``ctx.fail(path, rule, got)`` and ``ctx.error(path, message)`` make the
:class:`~batch.setfile.SetFileError` that names the file, the line and the key.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping, Sequence


def check_keys(ctx, data: object, path: list, valid: Sequence[str], what: str = "a table") -> dict:
    """``data`` as a dict when it is a table of only ``valid`` keys; else the error naming the key, with the
    closest valid key as a hint."""
    if not isinstance(data, Mapping):
        raise ctx.fail(path, f"{what} with keys {list(valid)}", data)
    for key in data:
        if key not in valid:
            close = difflib.get_close_matches(key, valid, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ctx.error(path + [key], f"unknown key {key!r}{hint}; valid keys are {list(valid)}")
    return dict(data)


def integer(ctx, value: object, path: list, minimum: int) -> int:
    """``value`` when it is an integer (not a bool) of at least ``minimum``; else the error naming the key."""
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        raise ctx.fail(path, f"an integer >= {minimum}", value)
    return value
