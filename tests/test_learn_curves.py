"""`cosim learn curves` plots the training's own validations, not the lines `cosim learn validate` adds."""

from __future__ import annotations

from cosim.learn.curves import own_validations


def test_curves_leave_out_the_lines_validate_appends():
    rows = [{"step": 1, "loss": 2.0}, {"step": 2, "val": {"AP30": 10.0, "AP50": 1.0}},
            {"step": 4, "val": {"AP30": 20.0, "AP50": 2.0}},
            {"step": 2, "val": {"AP30": 12.0, "AP50": 1.5}, "split": "val", "every": 2},
            {"step": 4, "val": {"AP30": 19.0, "AP50": 1.8}, "split": "val", "every": 2}]
    assert [(r["step"], r["val"]["AP30"]) for r in own_validations(rows)] == [(2, 10.0), (4, 20.0)]
