"""Every config key with its type, default and meaning, generated from the schema.

The meaning of a key is the comment on its line in `schema.py` (and a section's, its class
docstring), so the schema stays the one place where settings are documented.
"""

from __future__ import annotations

import ast
import inspect
import io
import textwrap
import tokenize
import typing
from dataclasses import dataclass, fields, is_dataclass
from functools import cache
from typing import Any, Literal

from pipeline.config import schema
from pipeline.config.choices import did_you_mean, nearest
from pipeline.config.loading import config_keys, toml_value, unknown_key
from pipeline.config.schema import Config
from pipeline.errors import UserError


@dataclass(frozen=True)
class KeyDoc:
    key: str  # dotted, as `--set` takes it
    type: str  # int, float, bool, str, a list, or the choices a|b|c
    default: str  # as TOML writes it
    meaning: str


@dataclass(frozen=True)
class SectionDoc:
    name: str  # "" for the top-level keys
    summary: str
    keys: list[KeyDoc]


@cache
def _comments() -> dict[tuple[str, str], str]:
    """(class name, field name) -> the comment on the field's line in schema.py."""
    source = inspect.getsource(schema)
    by_line = {
        token.start[0]: token.string.lstrip("#").strip()
        for token in tokenize.generate_tokens(io.StringIO(source).readline)
        if token.type == tokenize.COMMENT
    }
    found = {}
    for node in ast.parse(source).body:
        if isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                    found[(node.name, item.target.id)] = by_line.get(item.lineno, "")
    return found


def type_name(hint: Any) -> str:
    origin = typing.get_origin(hint)
    if origin is Literal:
        return "|".join(str(choice) for choice in typing.get_args(hint))
    if origin is tuple:
        return f"list of {type_name(typing.get_args(hint)[0])}"
    return getattr(hint, "__name__", str(hint))


def _keys(node: Any, prefix: str, skip: set[str]) -> list[KeyDoc]:
    hints = typing.get_type_hints(type(node))
    comments = _comments()
    return [
        KeyDoc(
            prefix + f.name,
            type_name(hints[f.name]),
            toml_value(getattr(node, f.name)),
            comments.get((type(node).__name__, f.name), ""),
        )
        for f in fields(node)
        if f.name not in skip
    ]


def _summary(cls: type) -> str:
    return (inspect.getdoc(cls) or "").split("\n\n")[0].replace("\n", " ")


def config_sections(config: Config, only: str | None = None) -> list[SectionDoc]:
    """The keys of `config` (their defaults are its values), by section; `only` picks a
    section (`tracking`) or one key (`tracking.method`, `preset`)."""
    sections = {f.name: getattr(config, f.name) for f in fields(config) if is_dataclass(getattr(config, f.name))}
    if only is not None and only not in sections:
        return [_one_key(config, only, sections)]
    found = []
    if only is None:
        found.append(SectionDoc("", _summary(Config), _keys(config, "", set(sections))))
    for name, node in sections.items():
        if only in (None, name):
            found.append(SectionDoc(name, _summary(type(node)), _keys(node, f"{name}.", set())))
    return found


def _one_key(config: Config, key: str, sections: dict[str, Any]) -> SectionDoc:
    """The section of `key` holding that key alone; UserError naming a wrong section or key,
    with the nearest names."""
    section = key.split(".")[0] if "." in key else ""
    if not section and not hasattr(config, key):
        keys = [k for k in config_keys(config) if k.endswith(f".{key}")]
        hint = did_you_mean(nearest(key, sections) or keys[:2])
        raise UserError(
            f"unknown config section '{key}'" + (f": {hint}" if hint else "") + " (every one: gsplatam config)"
        )
    if section and section not in sections:
        raise unknown_key(key)
    (found,) = [s for s in config_sections(config, section or None) if s.name == section]
    docs = [k for k in found.keys if k.key == key]
    if not docs:
        raise unknown_key(key)
    return SectionDoc(found.name, found.summary, docs)


LINE_WIDTH = 100  # characters: longer lines are wrapped, their continuation indented


def wrapped(line: str, indent: int, width: int = LINE_WIDTH) -> str:
    """`line` folded at spaces to `width` characters, the continuations indented by `indent`
    (a word longer than the line stays whole)."""
    return textwrap.fill(
        line, width=width, subsequent_indent=" " * indent, break_long_words=False, break_on_hyphens=False
    )


def format_sections(sections: list[SectionDoc]) -> str:
    """A plain-text table: one entry per key (key, type, default, meaning: lines of at most
    LINE_WIDTH characters, a meaning wrapped under itself), a heading per section."""
    rows = [k for s in sections for k in s.keys]
    key_w = max(len(k.key) for k in rows)
    type_w = min(max(len(k.type) for k in rows), 24)
    default_w = min(max(len(k.default) for k in rows), 16)
    lines = []
    for section in sections:
        lines.append(wrapped(f"[{section.name}]  {section.summary}" if section.name else section.summary, 4))
        for k in section.keys:
            head = f"  {k.key:<{key_w}}  {k.type:<{type_w}}  {k.default:<{default_w}}  "
            if len(head) > LINE_WIDTH // 2:  # a long key, type or default: the meaning on the next line
                lines += [head.rstrip(), wrapped(" " * (key_w + 4) + k.meaning, key_w + 4)]
            else:
                lines.append(wrapped(head + k.meaning, len(head)).rstrip())
        lines.append("")
    return "\n".join(lines)
