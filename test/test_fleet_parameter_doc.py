"""docs/fleet.md's parameter list is generated from the parameter tables
(fleet.parameter_doc) and must match them: this test fails when a parameter is added, removed
or changed without `python -m mapf_fleet.fleet.parameter_doc` run."""

from __future__ import annotations

import pytest

from mapf_fleet.fleet import parameter_doc as D
from mapf_fleet.fleet import parameters as P


def test_the_doc_lists_the_tables_parameters():
    assert D.documented(D.DOC.read_text()) == D.render(), (
        "docs/fleet.md's parameter list differs from mapf_fleet/fleet/parameters.py: run "
        "python -m mapf_fleet.fleet.parameter_doc")


def test_every_parameter_has_its_row_with_option_and_default():
    text = D.render()
    for table in (P.SIMULATOR, P.AGGREGATOR, P.POLICY):
        for name, param in table.items():
            option = f"`{param.option.flag}`" if param.option else ""
            assert f"| `{name}` | {option} | " in text, name
    assert "| `device` | `--device` | `'auto'` |" in text
    assert "| `guidance` | `--guidance` | `'highways'` |" in text  # the fleet's, FLEET_GUIDANCE


def test_the_check_fails_on_a_doc_that_differs_and_the_update_mends_it(tmp_path, monkeypatch,
                                                                         capsys):
    doc = tmp_path / "fleet.md"
    doc.write_text(D.updated(D.DOC.read_text()))
    assert D.main(["--check", "--doc", str(doc)]) == 0
    monkeypatch.setitem(P.POLICY, "new_knob", P.Param(1.5, "a knob added to the table"))
    assert D.main(["--check", "--doc", str(doc)]) == 1
    assert f"{doc}: the parameter list differs" in capsys.readouterr().err
    assert D.main(["--doc", str(doc)]) == 0  # rewritten from the table
    assert "| `new_knob` |  | `1.5` |  | a knob added to the table |" in doc.read_text()
    assert D.main(["--check", "--doc", str(doc)]) == 0
    doc.write_text("# no list\n")
    with pytest.raises(ValueError, match=f"{doc}: no generated parameter list"):
        D.main(["--check", "--doc", str(doc)])
