"""One way for the worker's settings dataclasses to refuse bad values."""

from __future__ import annotations

from models.errors import InvalidInputError


def refuse_invalid(what: str, checks: dict[str, bool]) -> None:
    """Raise :class:`InvalidInputError` naming every failed check (text -> passed)."""
    problems = [text for text, ok in checks.items() if not ok]
    if problems:
        raise InvalidInputError(f"invalid {what} settings: {'; '.join(problems)}")
