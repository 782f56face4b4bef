"""Strict YAML reading for hand-written files: YAML 1.2 scalars, duplicate keys are errors, every failure is one
clear line.

PyYAML silently keeps the last of two equal mapping keys, so a copy-paste slip in a hand-edited file changes its
meaning without a word; `load_yaml` refuses it. PyYAML also resolves plain scalars by YAML 1.1's rules, which
surprise: `010` is octal 8, `1:30` sexagesimal 90, `yes`/`no`/`on`/`off` booleans, `1e3` and `1e-3` strings (no
dot), `2024-01-02` a date. `StrictLoader` resolves them by the YAML 1.2 core schema instead (spec 1.2.2, 10.3.2):
null, true/false, decimal, 0o octal and 0x hex integers, floats with optional dot and exponent, .inf and .nan;
everything else is a string. Explicit tags (`!!int 010`) are constructed by the same rules. Every way reading or parsing can fail (I/O, encoding, syntax,
constructor errors such as an impossible date, nesting too deep for the recursive composer) becomes a `YamlError`
whose message is a single line starting with `where`.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import yaml

__all__ = ["YamlError", "StrictLoader", "load_yaml", "dump_yaml"]

_MERGE_TAG = "tag:yaml.org,2002:merge"


class YamlError(ValueError):
    """A YAML file or text could not be read or parsed; the message is one line naming where."""


# The YAML 1.2 core schema's plain scalars (spec 1.2.2, 10.3.2), each with the first characters it can start with.
_CORE = "tag:yaml.org,2002:"
_NULL = re.compile(r"^(?:~|null|Null|NULL|)$")
_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")
_INT = re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$")
_FLOAT = re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
                    r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$")
_DIGITS = "0123456789"


class StrictLoader(yaml.SafeLoader):
    """SafeLoader with YAML 1.2 core-schema scalars that raises on duplicate mapping keys (keys that would collide
    in the resulting dict)."""

    yaml_implicit_resolvers: dict = {}  # replaced, not extended: none of YAML 1.1's (filled in below)

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            self._check_unique_keys(node)
        return super().construct_mapping(node, deep=deep)

    def _check_unique_keys(self, node: yaml.MappingNode) -> None:
        # Checked on the raw node, before `<<` merge keys are flattened in: a key given explicitly next to a merged
        # one is YAML's documented way to override it, not a duplicate.
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == _MERGE_TAG:
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)  # explicitly: `set in seen` would quietly look the set up as a frozenset
            except TypeError:  # a list, mapping or set used as a key
                raise yaml.constructor.ConstructorError(None, None, f"unhashable key {key!r}",
                                                        key_node.start_mark) from None
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}", key_node.start_mark)
            seen.add(key)


def _scalar_error(loader: StrictLoader, node, kind: str):
    return yaml.constructor.ConstructorError(None, None, f"{node.value!r} is not a YAML 1.2 {kind}", node.start_mark)


def _construct_int(loader: StrictLoader, node) -> int:
    value = loader.construct_scalar(node)
    if not _INT.match(value):
        raise _scalar_error(loader, node, "integer")
    if value.startswith(("0o", "0x")):
        return int(value[2:], 8 if value[1] == "o" else 16)
    return int(value, 10)  # a leading zero is decimal: 010 is 10


def _construct_float(loader: StrictLoader, node) -> float:
    value = loader.construct_scalar(node)
    if _INT.match(value) and not value.startswith(("0o", "0x")):
        return float(int(value, 10))
    if not _FLOAT.match(value):
        raise _scalar_error(loader, node, "float")
    lower = value.lower()
    if lower.endswith(".inf"):
        return -math.inf if lower.startswith("-") else math.inf
    return math.nan if lower == ".nan" else float(value)


def _construct_bool(loader: StrictLoader, node) -> bool:
    value = loader.construct_scalar(node)
    if not _BOOL.match(value):
        raise _scalar_error(loader, node, "boolean")
    return value.lower() == "true"


def _construct_null(loader: StrictLoader, node) -> None:
    value = loader.construct_scalar(node)
    if not _NULL.match(value):
        raise _scalar_error(loader, node, "null")


for _tag, _regexp, _first in (("null", _NULL, ["~", "n", "N", ""]), ("bool", _BOOL, list("tTfF")),
                              ("int", _INT, [*_DIGITS, "-", "+"]), ("float", _FLOAT, [*_DIGITS, "-", "+", "."])):
    StrictLoader.add_implicit_resolver(_CORE + _tag, _regexp, _first)
StrictLoader.add_implicit_resolver(_MERGE_TAG, re.compile(r"^(?:<<)$"), ["<"])  # merge keys stay (not 1.2, but used)
for _tag, _constructor in (("null", _construct_null), ("bool", _construct_bool), ("int", _construct_int),
                           ("float", _construct_float)):
    StrictLoader.add_constructor(_CORE + _tag, _constructor)


class _QuotingDumper(yaml.SafeDumper):
    """SafeDumper that quotes a string either YAML 1.1 or 1.2 would read as something else (`1e3` is a float to
    `StrictLoader`, `yes` a boolean to YAML 1.1 tools), so that what it writes reads back as written."""


for _first, _resolvers in StrictLoader.yaml_implicit_resolvers.items():
    for _tag, _regexp in _resolvers:
        _QuotingDumper.add_implicit_resolver(_tag, _regexp, [_first])


def dump_yaml(obj, **kwargs) -> str:
    """YAML text of `obj` (plain data) that `load_yaml` reads back equal."""
    return yaml.dump(obj, Dumper=_QuotingDumper, **kwargs)


def load_yaml(text_or_path: str | os.PathLike, where: str):
    """The single document in `text_or_path` (a str is YAML text; a path-like is a file to read), None when empty.

    Raises YamlError("{where}: ...") — one line — for anything that cannot be read or parsed.
    """
    text = _read_text(Path(text_or_path), where) if isinstance(text_or_path, os.PathLike) else text_or_path
    try:
        return yaml.load(text, Loader=StrictLoader)  # noqa: S506 — StrictLoader is a SafeLoader
    except yaml.MarkedYAMLError as e:
        raise YamlError(f"{where}: not valid YAML{_position(e)}: {_one_line(e.problem or e.context or str(e))}") \
            from None
    except yaml.YAMLError as e:
        raise YamlError(f"{where}: not valid YAML: {_one_line(str(e))}") from None
    except RecursionError:
        raise YamlError(f"{where}: not valid YAML: nested too deeply") from None
    except (ValueError, OverflowError) as e:  # e.g. a date like 2024-13-45, an integer with too many digits
        raise YamlError(f"{where}: not valid YAML: {_one_line(str(e))}") from None
    except Exception as e:  # noqa: BLE001
        # PyYAML's constructors are not hardened against explicitly tagged garbage (`!!bool foo` raises KeyError,
        # `!!timestamp x` AttributeError, `!!int ''` IndexError); parsing text has no side effects, so any failure
        # means the text is unusable.
        raise YamlError(f"{where}: not valid YAML: cannot construct a value ({type(e).__name__}: "
                        f"{_one_line(str(e))})") from None


def _read_text(path: Path, where: str) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except OSError as e:
        raise YamlError(f"{where}: cannot read ({e.strerror or type(e).__name__})") from None
    except UnicodeDecodeError as e:
        raise YamlError(f"{where}: not UTF-8 text (byte {e.start})") from None


def _position(e: yaml.MarkedYAMLError) -> str:
    mark = e.problem_mark or e.context_mark
    return f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""


def _one_line(text: str) -> str:
    return " ".join(str(text).split())
