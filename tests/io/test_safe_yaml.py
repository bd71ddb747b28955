"""The bounded YAML/JSON reader: alias bombs, recursive anchors and duplicate keys are refused fast."""

import time

import pytest

from geocd.io.safe_yaml import MAX_ALIASES, YAMLLimitError, load_json, load_yaml

BOMB = (
    "\n".join(
        ["a: &a [x, x, x, x, x, x, x, x, x]"]
        + [f"{c}: &{c} [{', '.join(['*' + p] * 9)}]" for p, c in zip("abcdefgh", "bcdefghi")]
    )
    + "\n"
)


def test_billion_laughs_is_refused_fast():
    t = time.perf_counter()
    with pytest.raises(YAMLLimitError, match="expand to more than"):
        load_yaml(BOMB)
    assert time.perf_counter() - t < 2.0


def test_too_many_aliases():
    text = "a: &a 1\nb: [" + ", ".join(["*a"] * (MAX_ALIASES + 1)) + "]\n"
    with pytest.raises(YAMLLimitError, match=f"more than {MAX_ALIASES} YAML aliases"):
        load_yaml(text)


def test_few_aliases_still_load():
    assert load_yaml("a: &a {x: 1}\nb: *a\nc: [*a, *a]\n") == {"a": {"x": 1}, "b": {"x": 1}, "c": [{"x": 1}] * 2}


def test_recursive_anchor_is_refused():
    with pytest.raises(YAMLLimitError, match="recursive"):
        load_yaml("a: &a [1, *a]\n")


def test_duplicate_key_names_key_and_lines():
    with pytest.raises(YAMLLimitError, match=r"duplicate key 'name' at line 3 \(first at line 1\)"):
        load_yaml("name: a\nepochs: []\nname: b\n")
    with pytest.raises(YAMLLimitError, match="duplicate key 'path' at line 3"):
        load_yaml("images:\n  - path: a.tif\n    path: b.tif\n")


def test_merge_keys_are_not_duplicates():
    assert load_yaml("base: &b {x: 1, y: 2}\nc:\n  <<: *b\n  y: 3\n")["c"] == {"x": 1, "y": 3}


def test_plain_documents():
    assert load_yaml("") is None
    assert load_yaml("- 1\n- 2\n") == [1, 2]
    assert load_json('{"a": {"b": [1, 2]}}') == {"a": {"b": [1, 2]}}


def test_json_duplicate_key():
    with pytest.raises(YAMLLimitError, match="duplicate key 'a'"):
        load_json('{"a": 1, "a": 2}')
