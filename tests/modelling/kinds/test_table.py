"""The table of model kinds: the names the params accept, each kind's own params section in its module,
and the report's names and colours."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from needlecue_runtime.vocab import KINDS
from pipeline.config import InputParams, load_section
from pipeline.modelling.kinds import TABLE, kind_label, kind_of
from pipeline.modelling.kinds.ls import LS
from pipeline.reporting.style import COLORS


def test_the_table_holds_the_kinds_the_params_accept_in_their_order() -> None:
    # given / when: the table's names and the kinds vocab gives the params (simplest first)
    # then: the same kinds in the same order, each listed under its own name
    assert tuple(TABLE) == KINDS
    assert all(kind.name == name for name, kind in TABLE.items())


@pytest.mark.parametrize("name", KINDS)
def test_every_kind_reads_inputs_from_its_own_params_section(name: str) -> None:
    # given: a kind's params section with its defaults
    params = kind_of(name).params()
    # when / then: it says what the model reads, which the train stage and the inputs choice need
    assert isinstance(params.inputs, InputParams)  # type: ignore[attr-defined]


def test_an_unknown_kind_is_named_with_what_could_not_be_done() -> None:
    with pytest.raises(ValueError, match=r"cannot export model kind 'gru'; expected one of ls, fnn, lstm"):
        kind_of("gru", "export")


@pytest.mark.parametrize("name", KINDS)
def test_a_kinds_params_section_lives_in_its_module_and_a_typo_in_it_fails(name: str, tmp_path: Path) -> None:
    # given: a kind and a params.yaml whose section of it has a misspelt key
    kind = kind_of(name)
    path = tmp_path / "params.yaml"
    path.write_text(f"{name}:\n  inputz: {{kind: volts}}\n")
    # when / then: its section is a class of its own module, and reading the typo fails, naming it
    assert kind.params.__module__ == type(kind).__module__
    with pytest.raises(ValidationError, match="inputz"):
        load_section(kind.params, name, path)


def test_the_reports_names_and_colours_come_from_the_table(monkeypatch: pytest.MonkeyPatch) -> None:
    # given: the table's kinds, and a new kind put in it alone
    class Gru(LS):
        name = "gru"
        color = None

    monkeypatch.setitem(TABLE, "gru", Gru())
    # then: each kind is named by its label and drawn in its colour; any other name in capitals
    assert [kind_label(k) for k in TABLE] == ["LS", "FNN", "LSTM", "GRU"]
    assert kind_label("champion") == "CHAMPION"
    assert {k: COLORS[k] for k in KINDS} == {k: TABLE[k].color for k in KINDS}
    assert "gru" not in COLORS  # no colour of its own: matplotlib's next
