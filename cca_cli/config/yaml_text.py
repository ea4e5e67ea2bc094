"""Reading YAML files safely: text checks, duplicate keys, bounded aliases and nesting, short echoes.

Configs and manifests are read through :func:`read_yaml_file`, which refuses
what is not a YAML text file (a folder, a pipe, binary data), a document whose
aliases would expand into millions of nodes (a "billion laughs"), nesting too
deep to walk, and a key given twice in one mapping (PyYAML would silently keep
the last one). Error messages quote at most a short piece of what the user
wrote (:func:`cca_cli.errors.short`), and never the contents of a file that is not what was
asked for.
"""

from __future__ import annotations

import stat
from pathlib import Path
from typing import Any

import yaml

from cca_cli.errors import ConfigError, InputError, short

__all__ = ["MAX_NODES", "MAX_DEPTH", "read_text_file", "parse_yaml", "read_yaml_file"]

#: Largest number of nodes a document may expand to (aliases counted at every use).
MAX_NODES = 200_000
#: Deepest nesting of collections.
MAX_DEPTH = 100


def read_text_file(path: str | Path, *, what: str = "config") -> str:
    """The UTF-8 text of a regular file, with one-line errors naming ``path``.

    Raises
    ------
    ConfigError
        For a config (``what="config"``): missing, not a regular file, unreadable or not text.
    InputError
        The same for any other ``what`` (a manifest, a table …).
    """
    path = Path(path)
    error = ConfigError if what == "config" else InputError
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        hint = ("give an existing YAML file or omit it for the built-in default" if what == "config"
                else "check the path")
        raise error(f"{path}: {what} file not found; {hint}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    if stat.S_ISDIR(mode):
        raise error(f"{path}: is a folder, not a {what} file")
    if not (stat.S_ISREG(mode) or str(path) == "/dev/null"):
        raise error(f"{path}: is not a regular file (a pipe or device); give a {what} file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise error(f"{path}: not a text file (not UTF-8); give a YAML {what}") from None


class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """SafeLoader (libyaml's when present: it also reads deep nesting quickly) that refuses duplicate keys."""


def _construct_mapping(loader: _Loader, node: yaml.MappingNode, deep: bool = False):
    loader.flatten_mapping(node)
    seen = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            duplicate = key in seen
        except TypeError:
            continue  # an unhashable key: PyYAML's own constructor refuses it below
        if duplicate:
            first, again = seen[key] + 1, key_node.start_mark.line + 1
            lines = f"lines {first} and {again}" if first != again else f"line {first}"
            raise yaml.constructor.ConstructorError(
                None, None, f"key {short(key, 40)} is given twice ({lines}); keep one", key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def _check_size(node: yaml.Node, source: str) -> None:
    """Refuse documents that expand to more than MAX_NODES nodes or nest deeper than MAX_DEPTH."""
    sizes: dict[int, int] = {}

    def size(n: yaml.Node, depth: int) -> int:
        if depth > MAX_DEPTH:
            raise ConfigError(f"{source}: nested more than {MAX_DEPTH} levels deep; is this a cca file?")
        if id(n) in sizes:
            return sizes[id(n)]
        sizes[id(n)] = 1  # a node that contains itself counts once
        if isinstance(n, yaml.SequenceNode):
            total = 1 + sum(size(child, depth + 1) for child in n.value)
        elif isinstance(n, yaml.MappingNode):
            total = 1 + sum(size(k, depth + 1) + size(v, depth + 1) for k, v in n.value)
        else:
            total = 1
        if total > MAX_NODES:
            raise ConfigError(f"{source}: expands to more than {MAX_NODES} values (YAML aliases used over and "
                              "over); write the values out or remove the aliases")
        sizes[id(n)] = total
        return total

    size(node, 0)


def _syntax_error(source: str, exc: yaml.YAMLError) -> str:
    """One line naming where the YAML goes wrong: the line a construct that is never closed begins on (a
    bracket left open), else the line where the parser found the problem."""
    mark = getattr(exc, "problem_mark", None)
    context = getattr(exc, "context_mark", None)
    problem = getattr(exc, "problem", None) or "not valid YAML"
    if context is not None and mark is not None and context.line < mark.line and getattr(exc, "context", None):
        return (f"{source}: line {context.line + 1}: not valid YAML ({exc.context} begun there: {problem} on "
                f"line {mark.line + 1})")
    where = f" line {mark.line + 1}:" if mark else ""
    return f"{source}:{where} not valid YAML ({problem})"


def parse_yaml(text: str, *, source: str) -> Any:
    """Parse YAML ``text`` (``source`` names it in errors) into Python data.

    Raises
    ------
    ConfigError
        A syntax error, a duplicate key, or a document too large or too deep.
    """
    try:
        loader = _Loader(text)
        try:
            node = loader.get_single_node()
            if node is None:
                return None
            _check_size(node, source)
            return loader.construct_document(node)
        finally:
            if hasattr(loader, "dispose"):
                loader.dispose()
    except yaml.YAMLError as exc:
        raise ConfigError(_syntax_error(source, exc)) from None
    except RecursionError:
        raise ConfigError(f"{source}: nested too deeply to read; is this a cca file?") from None


def read_yaml_file(path: str | Path, *, what: str = "config") -> Any:
    """:func:`read_text_file` then :func:`parse_yaml`; an empty document (or only comments) gives None."""
    return parse_yaml(read_text_file(path, what=what), source=str(path))
