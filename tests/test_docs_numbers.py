"""The number tables of docs/ are marked for benchmarks/docs_numbers.py: well-formed markers, one producer per
name, the producing command beside each table. Fast: nothing is run (the regeneration itself is the script)."""

from __future__ import annotations

import pytest

from benchmarks.docs_numbers import DOCS, PRODUCERS, MarkerError, blocks, doc_blocks, main


def test_every_marked_table_in_docs_has_a_producer_and_its_command_beside_it():
    found = doc_blocks()
    names = [n for bs in found.values() for n, _, _ in bs]
    assert {"eval_coverage", "eval_coverage_strict", "eval_oracle", "eval_oracle_ladder", "comm_urban"} <= set(names)
    assert len(names) == len(set(names)), f"a table name is used twice across docs/: {sorted(names)}"
    assert set(names) <= PRODUCERS.keys(), f"no producer for {sorted(set(names) - PRODUCERS.keys())}"
    assert set(PRODUCERS) <= set(names), f"producers without a table in docs/: {sorted(set(PRODUCERS) - set(names))}"
    for path, bs in found.items():
        text = path.read_text(encoding="utf-8")
        for name, start, end in bs:
            before = text[max(0, start - 700):start]
            assert "cosim " in before, f"{path.name}: no command shown before the table {name}"
            assert text[start:end].strip(), f"{path.name}: the table {name} is empty"


def test_marker_parser_finds_bodies_and_refuses_malformed_markers():
    text = "a\n<!-- docs_numbers:x -->\n| 1 |\n<!-- /docs_numbers:x -->\nb\n"
    [(name, start, end)] = blocks(text)
    assert (name, text[start:end]) == ("x", "| 1 |\n")
    bad = {
        "never closed": "<!-- docs_numbers:x -->\n| 1 |\n",
        "not open": "<!-- /docs_numbers:x -->\n",
        "opens inside": "<!-- docs_numbers:x -->\n<!-- docs_numbers:y -->\n<!-- /docs_numbers:y -->\n"
                        "<!-- /docs_numbers:x -->\n",
        "appears twice": "<!-- docs_numbers:x -->\n<!-- /docs_numbers:x -->\n" * 2,
        "is not": "<!-- docs_numbers:Bad-Name -->\n<!-- /docs_numbers:Bad-Name -->\n",
        "alone on its line": "<!-- docs_numbers:x -->\n<!-- /docs_numbers:x -->\nsee <!-- docs_numbers:y -->\n",
    }
    for message, doc in bad.items():
        with pytest.raises(MarkerError, match=message):
            blocks(doc, "doc.md")


def test_an_unknown_table_name_is_refused_with_exit_status_2(capsys):
    assert main(["--only", "no_such_table"]) == 2
    err = capsys.readouterr().err
    assert "no_such_table" in err and "eval_coverage" in err
    assert DOCS.is_dir()


# ------------------------------------------------------------------------------------------- pedestrian sizes


def test_docs_pedestrian_sizes_are_the_labelled_boxes():
    """docs/events.md's pedestrian sizes are what ``people.posed_box`` labels (issue 37: it said every box was
    0.5 x 0.6 x 1.75 m while statures vary from child to tall adult)."""
    from benchmarks.docs_numbers import DOCS, blocks, pedestrian_boxes

    text = (DOCS / "events.md").read_text()
    [(start, end)] = [(s, e) for name, s, e in blocks(text) if name == "pedestrian_boxes"]
    assert text[start:end] == pedestrian_boxes()
    assert "0.5 x 0.6 x 1.75" not in text
