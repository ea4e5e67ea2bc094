"""Reading YAML files safely: duplicate keys, alias bombs, deep nesting, files that are not text."""

import os

import pytest

from cca_cli.config.yaml_text import MAX_NODES, parse_yaml, read_yaml_file
from cca_cli.errors import ConfigError, InputError


def test_plain_yaml_and_aliases_within_bounds():
    assert parse_yaml("a: &x [1, 2]\nb: *x\n", source="s") == {"a": [1, 2], "b": [1, 2]}
    assert parse_yaml("# only a comment\n", source="s") is None


@pytest.mark.parametrize(("text", "message"), [
    ("a: 1\nb: 2\na: 3\n", "key 'a' is given twice \\(lines 1 and 3\\)"),
    ("a: {x: 1, x: 2}\n", "key 'x' is given twice \\(line 1\\)"),
    ("a: [1,\n", "line 2: not valid YAML"),
    ("a: 1\narray:\n  grid: [9\n  overlap: 0.6\n", "line 3: not valid YAML \\(while parsing a flow sequence begun "
                                                    "there: .* on line 4\\)"),   # the bracket left open
    ("a: " + "[" * 500 + "]" * 500, "nested more than"),
])
def test_refused_documents(text, message):
    with pytest.raises(ConfigError, match=message):
        parse_yaml(text, source="s")


def test_an_alias_bomb_is_refused_before_it_expands():
    lines = ["l0: &l0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"l{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * 10) + "]" for i in range(1, 9)]
    with pytest.raises(ConfigError, match=str(MAX_NODES)):
        parse_yaml("\n".join(lines), source="s")


def test_files_that_are_not_yaml_text(tmp_path):
    (tmp_path / "bin.yaml").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(ConfigError, match="not a text file"):
        read_yaml_file(tmp_path / "bin.yaml")
    with pytest.raises(ConfigError, match="is a folder"):
        read_yaml_file(tmp_path)
    os.mkfifo(tmp_path / "pipe.yaml")
    with pytest.raises(InputError, match="not a regular file"):
        read_yaml_file(tmp_path / "pipe.yaml", what="manifest")
    with pytest.raises(ConfigError, match="not found"):
        read_yaml_file(tmp_path / "missing.yaml")
