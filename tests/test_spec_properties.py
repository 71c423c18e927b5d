"""Spec validation as properties (hypothesis): an invalid value of any field — NaN or ±inf, a negative
count, a bool where a number belongs, an unknown choice, a value of the wrong type — is refused with a
SpecError of one line, whether it comes through CellSpec(...) or CellSpec.from_dict (text, TOML, JSON);
a valid value round-trips through to_dict/from_dict and through its text form (`--set KEY=VALUE`); and
no value of any type makes resolution fail with anything but a SpecError."""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from asp_dist.core.registry import DOMAINS
from asp_dist.spec import (
    _OPTIONAL,
    CHOICES,
    FIELD_NAMES,
    INT64_MAX,
    METHODS,
    CellSpec,
    SpecError,
    coerce_field,
    field_type,
)

SETTINGS = settings(max_examples=60, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
BASE = {"domain": "signaling"}

ALLOWED = {**CHOICES, "domain": tuple(sorted(DOMAINS)), "method": tuple(sorted(METHODS))}
FLOATS = [n for n in FIELD_NAMES if field_type(n) is float]
INTS = [n for n in FIELD_NAMES if field_type(n) is int]
BOOLS = [n for n in FIELD_NAMES if field_type(n) is bool]
STRS = [n for n in FIELD_NAMES if field_type(n) is str]
# Text fields without choices are a domain's own (a PettingZoo domain's env, agent and channel), which the
# domain checks when a cell of it resolves; every common text field is a choice.
FREE_TEXT = set(STRS) - set(ALLOWED)
assert FREE_TEXT <= {k.name for d in DOMAINS.values() for k in d.knobs}, "every common text field is a choice"

wrong_containers = st.one_of(st.lists(st.integers(), max_size=2), st.dictionaries(st.text(max_size=3), st.integers(),
                                                                                  max_size=1))
not_a_number_text = st.text(max_size=12).filter(lambda s: not _parses_as_float(s) and s.strip().lower() != "none")


def _parses_as_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def invalid_value(name: str) -> st.SearchStrategy:
    t = field_type(name)
    common = [wrong_containers] + ([] if name in _OPTIONAL else [st.none()])
    if t is float:
        return st.one_of(st.sampled_from([math.nan, math.inf, -math.inf, "nan", "inf", "-inf"]), st.booleans(),
                         st.floats(max_value=-1e-9, allow_nan=False, allow_infinity=False), not_a_number_text,
                         *common)
    if t is int:
        return st.one_of(st.booleans(), st.integers(max_value=-1), st.integers(min_value=INT64_MAX + 1),
                         st.floats(allow_nan=True, allow_infinity=True).filter(lambda x: not float(x).is_integer()),
                         st.sampled_from(["nan", "inf", "true", "1.5", ""]), not_a_number_text, *common)
    if t is bool:
        return st.one_of(st.integers().filter(lambda i: i not in (0, 1)), st.floats(),
                         st.text(max_size=8).filter(lambda s: s.strip().lower() not in
                                                    ("0", "1", "true", "false", "yes", "no", "on", "off")),
                         *common)
    if name in FREE_TEXT:  # any text is a value of the field; the wrong type is not
        return st.one_of(st.integers(), st.booleans(), st.floats(), *common)
    return st.one_of(st.text(max_size=20).filter(lambda s: s not in ALLOWED[name]), st.integers(), st.booleans(),
                     st.floats(), *common)


def valid_value(name: str) -> st.SearchStrategy:
    t = field_type(name)
    if t is str:
        return st.text(max_size=12) if name in FREE_TEXT else st.sampled_from(ALLOWED[name])
    if t is bool:
        values = st.booleans()
    elif t is int:
        values = st.integers(min_value=0, max_value=INT64_MAX)
    else:
        values = st.floats(min_value=0.0, max_value=1e300, allow_nan=False, allow_infinity=False)
    return st.one_of(values, st.none()) if name in _OPTIONAL else values


def field_and(value_strategy) -> st.SearchStrategy:
    return st.sampled_from(FIELD_NAMES).flatmap(lambda name: st.tuples(st.just(name), value_strategy(name)))


def refused_in_one_line(make) -> str:
    with pytest.raises(SpecError) as err:
        make().resolved()
    message = str(err.value)
    assert message.strip() and "\n" not in message and "\r" not in message, repr(message)
    return message


@SETTINGS
@given(field_and(invalid_value))
def test_an_invalid_value_is_refused_in_one_line(pair):
    name, value = pair
    changes = {**BASE, name: value}
    refused_in_one_line(lambda: CellSpec.from_dict(changes))  # text, TOML, JSON: coerced, then validated
    refused_in_one_line(lambda: CellSpec(**changes))  # Python callers: validated without coercion


@pytest.mark.parametrize("name", FLOATS)
@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_every_float_knob_refuses_non_finite_text(name, bad):
    message = refused_in_one_line(lambda: CellSpec.from_dict({**BASE, name: bad}))
    assert name in message


@pytest.mark.parametrize("name", INTS)
def test_no_integer_knob_takes_a_bool(name):
    for value in (True, False):
        changes = {**BASE, name: value}
        assert name in refused_in_one_line(lambda changes=changes: CellSpec.from_dict(changes))
        assert name in refused_in_one_line(lambda changes=changes: CellSpec(**changes))


@SETTINGS
@given(field_and(valid_value))
def test_a_valid_value_round_trips(pair):
    name, value = pair
    spec = CellSpec(**{**BASE, name: value})
    assert CellSpec.from_dict(spec.to_dict()) == spec
    back = coerce_field(name, str(value))
    assert back == value and type(back) is type(value)


@SETTINGS
@given(field_and(lambda name: st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=10),
                                        wrong_containers)))
def test_resolution_fails_only_with_a_spec_error(pair):
    name, value = pair
    for make in (lambda: CellSpec.from_dict({**BASE, name: value}), lambda: CellSpec(**{**BASE, name: value})):
        try:
            make().resolved()
        except SpecError as err:
            assert "\n" not in str(err) and str(err).strip()
