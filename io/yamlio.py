"""Strict YAML reading for hand-written files: duplicate keys are errors, every failure is one clear line.

PyYAML silently keeps the last of two equal mapping keys, so a copy-paste slip in a hand-edited file changes its
meaning without a word; `load_yaml` refuses it. Every way reading or parsing can fail (I/O, encoding, syntax,
constructor errors such as an impossible date, nesting too deep for the recursive composer) becomes a `YamlError`
whose message is a single line starting with `where`.
"""

from __future__ import annotations

import os
from pathlib import Path

import yaml

__all__ = ["YamlError", "StrictLoader", "load_yaml"]

_MERGE_TAG = "tag:yaml.org,2002:merge"


class YamlError(ValueError):
    """A YAML file or text could not be read or parsed; the message is one line naming where."""


class StrictLoader(yaml.SafeLoader):
    """SafeLoader that raises on duplicate mapping keys (keys that would collide in the resulting dict)."""

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
