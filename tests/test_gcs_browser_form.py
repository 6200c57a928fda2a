"""The browser-form snapshot parser: everything but a well-formed record is refused with a reason."""

from __future__ import annotations

import json

import pytest

from groundstation.browser_form import FormSnapshot, parse_snapshot, storage_key
from groundstation.inputs import InputError

GOOD = {"token": "ab12", "seq": 3, "button": "Takeoff", "values": {"Targets": "1,3"}}


def test_a_well_formed_record_parses():
    snap = parse_snapshot(json.dumps(GOOD))
    assert snap == FormSnapshot(button="Takeoff", values={"Targets": "1,3"}, seq=3, token="ab12")
    assert snap.get("Targets") == "1,3"


def test_a_field_the_page_did_not_show_is_refused_by_name():
    with pytest.raises(InputError, match="Takeoff alt"):
        parse_snapshot(json.dumps(GOOD)).get("Takeoff alt (m)")


@pytest.mark.parametrize(
    ("raw", "why"),
    [
        (None, "no record"),
        ("", "malformed"),
        ("{", "malformed"),
        ("[]", "malformed"),
        (json.dumps({**GOOD, "seq": "3"}), "wrong types"),
        (json.dumps({**GOOD, "values": {"Targets": 3}}), "wrong types"),
        (json.dumps({**GOOD, "values": ["Targets"]}), "wrong types"),
        (json.dumps({k: v for k, v in GOOD.items() if k != "token"}), "malformed"),
    ],
)
def test_anything_else_is_refused_with_a_reason(raw, why):
    with pytest.raises(InputError, match=why):
        parse_snapshot(raw)


def test_each_install_has_its_own_key():
    assert storage_key("a") != storage_key("b")
