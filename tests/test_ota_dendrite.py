"""The fleet daemon (CogniPilot Dendrite) reads every latest.json we write and publish.

tests/_dendrite.py holds its acceptance rules, written from its Rust source (serde, serde_json,
chrono) without our writer's code; tests/conftest.py runs it after every successful
``ota build`` of the suite. Here: the checker against the rules it claims, then builds whose
latest.json carries history."""

from __future__ import annotations

import json
import shutil

import pytest

from tests._dendrite import Refused, check_download, check_release, chrono_datetime_utc, parse
from tests._ota import make_robot
from tests.conftest import CORPUS, PROJECT

FLEET = CORPUS / "firmware_releases"
GOOD = {
    "board": "b",
    "app": "a",
    "latest": {
        "version": "1.0.0",
        "date": "2026-01-13T12:00:00Z",
        "mcuboot_hash": "ab" * 32,
        "size": 1,
        "url": "https://x.example/b/a/1.0.0.bin",
        "changelog": "c",
    },
    "previous": [],
}


def _bytes(doc) -> bytes:
    return json.dumps(doc).encode()


def _with(path: str, value) -> bytes:
    doc = json.loads(json.dumps(GOOD))
    *parents, last = path.split(".")
    node = doc
    for p in parents:
        node = node[p]
    if value is _DELETE:
        del node[last]
    else:
        node[last] = value
    return _bytes(doc)


_DELETE = object()


@pytest.mark.parametrize(
    "data",
    [
        _with("latest.changelog", _DELETE),  # #[serde(default)] Option
        _with("latest.changelog", None),
        _with("previous", _DELETE),  # #[serde(default)] Vec
        _with("signature", "x"),  # unknown fields are ignored (no deny_unknown_fields) ...
        _with("latest.sha256", 5),  # ... at every level
        _with("latest.size", 2**64 - 1),
        _with("latest.mcuboot_hash", "not hex at all"),  # any String to the parser
        _with("latest.date", "2026-01-13 12:00:00+05:30"),  # chrono's relaxed RFC 3339
        _with("latest.date", "2026-01-13t12:00:00.5z"),
        _with("latest.date", "2026-1-3T1:2:3 UTC"),
        b'{"board": "b", "app": "a", "x": 1, "x": 2, "latest": ' + _bytes(GOOD["latest"]) + b"}",
        b'["b", "a", ' + _bytes(GOOD["latest"]) + b"]",  # serde's sequence form of a struct
        _bytes(GOOD) + b" \n\t\r",
    ],
)
def test_the_daemon_accepts(data):
    parse(data)


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (_with("latest.date", "2026-11-01"), "premature end of input"),  # the old example fixture
        (_with("latest.date", "2026-11-01T00:00:00"), "premature end of input"),  # no offset
        (_with("latest.date", "2026-02-30T00:00:00Z"), "out of range"),
        (_with("latest.date", "2026-01-01T00:00:00+24:00"), "out of range"),
        (_with("latest.date", "2026-01-01T00:00:00+01"), "premature end of input"),
        (_with("latest.date", 1767225600), "invalid type integer"),
        (_with("latest.size", 1.0), "floating point"),
        (_with("latest.size", -1), "expected u64"),
        (_with("latest.size", 2**64), "expected u64"),
        (_with("latest.size", "1"), "invalid type string"),
        (_with("latest.url", None), "invalid type null"),
        (_with("latest.changelog", 3), "invalid type integer"),
        (_with("latest.version", _DELETE), "missing field `version`"),
        (_with("latest.mcuboot_hash", _DELETE), "missing field `mcuboot_hash`"),
        (_with("app", _DELETE), "missing field `app`"),
        (_with("latest", _DELETE), "missing field `latest`"),
        (_with("previous", None), "expected a sequence"),
        (_with("previous", [{"version": "0.9.0"}]), "missing field `date`"),
        (b'{"board": "b", "board": "b", "app": "a", "latest": ' + _bytes(GOOD["latest"]) + b"}", "duplicate field"),
        (_bytes(GOOD).replace(b'"b"', b'"\\ud800"', 1), "lone surrogate"),
        (_bytes(GOOD).replace(b'"c"', b'"\x01"'), "not JSON"),
        (_bytes(GOOD).replace(b"1,", b"NaN,"), "not JSON"),
        (_bytes(GOOD) + b"x", "not JSON"),
        (b"\xef\xbb\xbf" + _bytes(GOOD), "byte order mark"),
        (_bytes(GOOD).decode().encode("utf-16"), "not UTF-8"),
        (b'["b", "a"]', "no element for `latest`"),
        (b"[]", "no element for `board`"),
    ],
)
def test_the_daemon_refuses(data, why):
    with pytest.raises(Refused, match=why.replace("(", r"\(")):
        parse(data)


def test_dates_convert_to_utc():
    assert chrono_datetime_utc("2026-01-01T00:30:00+01:00") == (2025, 12, 31, 23, 30, 0, 0)
    assert chrono_datetime_utc("2026-12-31T23:59:60-01:30") == (2027, 1, 1, 1, 29, 59, 1_000_000_000)


def test_the_fleets_own_files_and_our_example_are_read():
    found = sorted(FLEET.glob("*/*/latest.json"))
    assert len(found) >= 3
    for path in found:
        parse(path.read_bytes())
    example = PROJECT / "examples" / "robot" / "firmware" / "arm-ctrl.latest.json"
    assert parse(example.read_bytes()).latest.date == (2026, 11, 1, 0, 0, 0, 0)


def test_every_release_entry_is_read_and_downloads(cli, tmp_path):
    """Two releases: the second's previous[] holds the first and the fleet's own history."""
    robot = make_robot(tmp_path, cli)
    first, second = tmp_path / "rel1", tmp_path / "rel2"
    assert robot.build(cli, first, "--previous", FLEET, "--import-unsigned-history").exit_code == 0
    robot.rewrite(cli, flex_version="0.3.0")
    # the fleet's entries stay unsigned: carried on only with the same explicit choice (issue 16 §8)
    assert robot.build(cli, second, "--previous", first, "--import-unsigned-history").exit_code == 0
    assert check_release(second, "https://fw.example.com/r") == 2
    flex = parse((second / "mr_mcxn_t1" / "flex-io" / "latest.json").read_bytes())
    assert [r.version for r in (flex.latest, *flex.previous)] == ["0.3.0", "0.2.0", "0.1.0"]
    # the download check is real: a changed byte of the image, or a wrong size, is refused
    body = (second / "mr_mcxn_t1" / "flex-io" / "0.3.0.bin").read_bytes()
    check_download(flex.latest, body)
    with pytest.raises(Refused, match="MCUboot hash mismatch"):
        check_download(flex.latest, body[:100] + bytes([body[100] ^ 1]) + body[101:])
    with pytest.raises(Refused, match="size mismatch"):
        check_download(flex.latest, body + b"\0")


def test_a_previous_latest_json_the_daemon_refuses_is_not_carried_over(cli, tmp_path):
    """History is copied into the new latest.json: one date the daemon cannot parse there would
    make it refuse the new release too, so the build refuses it, naming the entry."""
    robot = make_robot(tmp_path, cli)
    prev = tmp_path / "prev"
    shutil.copytree(FLEET, prev)
    path = prev / "mr_mcxn_t1" / "flex-io" / "latest.json"
    doc = json.loads(path.read_text())
    doc["previous"] = [{**doc["latest"], "version": "0.0.9", "date": "2025-12-01"}]
    path.write_text(json.dumps(doc))
    r = robot.build(cli, tmp_path / "rel", "--previous", prev, "--import-unsigned-history")
    assert r.exit_code == 3, r.stderr
    assert "previous[0].date is not an RFC 3339 date and time" in r.stderr
    assert "2025-12-01" in r.stderr and "flex-io/latest.json" in r.stderr
    assert not (tmp_path / "rel").exists()
