"""Helpers shared by the add-on tests."""

from __future__ import annotations


class Reports:
    """Stands in for ``Operator.report``: collects (level, message)."""

    def __init__(self) -> None:
        self.items: list[tuple[str, str]] = []

    def __call__(self, levels, message: str) -> None:
        self.items.extend((level, message) for level in levels)

    def of(self, level: str) -> list[str]:
        return [message for lvl, message in self.items if lvl == level]
