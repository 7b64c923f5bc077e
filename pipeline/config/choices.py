"""A name that is not one of the known ones (a key, a section, a preset, a format), answered
with the nearest known names ("did you mean ...?", by difflib) rather than a list of them all."""

from __future__ import annotations

import difflib
from collections.abc import Iterable

from pipeline.errors import UserError


def nearest(word: str, choices: Iterable[str], most: int = 2) -> list[str]:
    """The known names closest to `word` by spelling (difflib's ratio at least 0.6), nearest first:
    the nearest one, and others only as near as it (within 0.05)."""
    scored = []
    for choice in choices:
        matcher = difflib.SequenceMatcher(None, word, choice)
        scored.append((matcher.ratio(), choice))
    scored.sort(key=lambda pair: -pair[0])
    if not scored or scored[0][0] < 0.6:
        return []
    best = scored[0][0]
    return [choice for ratio, choice in scored[:most] if ratio >= max(0.6, best - 0.05)]


def did_you_mean(candidates: list[str]) -> str:
    """`did you mean 'a'?` or `did you mean 'a' or 'b'?`; '' for none."""
    if not candidates:
        return ""
    return "did you mean " + " or ".join(f"'{c}'" for c in candidates) + "?"


def unknown_name(kind: str, word: str, choices: Iterable[str], listed: bool = True) -> UserError:
    """`unknown preset 'tinny': did you mean 'tiny'? (choose from base, small, tiny, tum)`; with
    `listed` False the choices are not listed (there are too many: the caller says where they are)."""
    names = list(choices)
    hint = did_you_mean(nearest(word, names))
    every = f" (choose from {', '.join(names)})" if listed else ""
    return UserError(f"unknown {kind} '{word}'" + (f": {hint}" if hint else "") + every)
