"""The table of model kinds: the names the params accept, each kind's own params section."""

from __future__ import annotations

import pytest

from pipeline.config import InputParams
from pipeline.modelling.kinds import TABLE, kind_of
from pipeline.vocab import KINDS


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
