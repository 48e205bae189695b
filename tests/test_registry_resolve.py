"""resolve --registry / verify --registry: a resolved tree checked against a published registry.

The registry is the corpus's (org.ros2, org.gazebosim, org.ieee.1722 and the operational
stream profile), published by the CLI and served on 127.0.0.1.
"""

from __future__ import annotations

import hashlib
import shutil

import pytest

from tests._registry import PASSPHRASE, PROFILE, serve_corpus_registry

GOOD_TOPIC = '<topic sensor="imu0" name="/imu" type="sensor_msgs/msg/Imu" qos="sensor_data"/>'
BAD_TOPIC = '<topic sensor="imu0" name="/imu" type="sensor_msgs/msg/Imu" qos="warp_speed"/>'


@pytest.fixture(autouse=True)
def _passphrase(monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """The corpus's domains and stream profile, published and served on 127.0.0.1."""
    with serve_corpus_registry(tmp_path_factory.mktemp("reg")) as served:
        yield served


def _robot(tmp_path, *, extension: str = "", profile: bytes | None = None, child: str | None = None):
    """robot.hcdf with one comp (optionally an extension), a network using profiles/op.streams.xml,
    and optionally an included child.hcdf; returns the root document's path."""
    (tmp_path / "profiles").mkdir(parents=True)
    data = profile if profile is not None else PROFILE.read_bytes()
    (tmp_path / "profiles" / "op.streams.xml").write_bytes(data)
    sha = hashlib.sha256(data).hexdigest()
    include = '<include uri="child.hcdf"/>\n' if child is not None else ""
    if child is not None:
        (tmp_path / "child.hcdf").write_text(f'<hcdf version="1.0">\n<comp name="c">\n{child}</comp>\n</hcdf>\n')
    doc = tmp_path / "robot.hcdf"
    doc.write_text(
        f'<hcdf version="1.0">\n{include}<comp name="a">\n{extension}</comp>\n'
        f'<network name="n"><stream-profile uri="profiles/op.streams.xml"\n'
        f'  sha="{sha}"/></network>\n</hcdf>\n'
    )
    return doc


def _ros2(topic: str = GOOD_TOPIC) -> str:
    return f'<extension domain="org.ros2" version="1.0"><topic-map>\n{topic}</topic-map></extension>\n'


def _resolve(cli, published, doc, *extra, site=None):
    reg, srv = published
    return cli("resolve", doc, "--registry", site or srv.base, "--trusted-root", reg.root_json, "--json", *extra)


def test_clean_tree_passes_and_writes_what_a_plain_resolve_writes(cli, published, tmp_path):
    reg, srv = published
    doc = _robot(tmp_path, extension=_ros2())
    lock = tmp_path / "robot.hcdf.lock"
    plain = cli("resolve", doc, "--json")
    assert plain.exit_code == 0, plain.stdout
    expected = lock.read_bytes()
    lock.unlink()
    before = srv.total_hits
    res = _resolve(cli, published, doc, "--out", tmp_path / "flat.hcdf")
    assert res.exit_code == 0, res.stdout
    assert res.json["errors"] == [] and res.json["warnings"] == []
    assert lock.read_bytes() == expected
    assert (tmp_path / "flat.hcdf").is_file()
    # the registry was asked: its timestamp, and the org.ros2 role and schema
    assert srv.total_hits > before
    assert any(path.endswith(".org.ros2.json") for path in srv.hits)
    assert any(path.startswith("/targets/extensions/org.ros2/") for path in srv.hits)


def test_unregistered_domain_is_a_warning_and_an_error_with_strict(cli, published, tmp_path):
    doc = _robot(tmp_path, extension='<extension domain="com.example.arm" version="1.0"><x/></extension>\n')
    lock = tmp_path / "robot.hcdf.lock"
    res = _resolve(cli, published, doc)
    assert res.exit_code == 0, res.stdout
    (warning,) = res.json["warnings"]
    assert warning == {
        "code": "extension-unregistered",
        "message": "extension domain 'com.example.arm' is not registered",
        "file": str(doc),
        "line": 3,
    }
    assert lock.is_file()
    lock.unlink()
    res = _resolve(cli, published, doc, "--strict")
    assert res.exit_code == 1
    (err,) = res.json["errors"]
    assert err["code"] == "extension-unregistered" and err["line"] == 3
    assert not lock.exists()


def test_human_output_shows_the_warning(cli, published, tmp_path):
    reg, srv = published
    doc = _robot(tmp_path, extension='<extension domain="org.ros2" version="9.0"><topic-map/></extension>\n')
    res = cli("resolve", doc, "--registry", srv.base, "--trusted-root", reg.root_json)
    assert res.exit_code == 0
    assert "warning: " in res.stderr and "org.ros2 version '9.0' is not registered (registered: 1.0)" in res.stderr


def test_extension_in_an_included_document_is_checked(cli, published, tmp_path):
    doc = _robot(tmp_path, child=_ros2(BAD_TOPIC))
    res = _resolve(cli, published, doc)
    assert res.exit_code == 1
    (err,) = res.json["errors"]
    assert err["code"] == "extension-content" and err["file"] == str(tmp_path / "child.hcdf") and err["line"] == 4
    assert not (tmp_path / "robot.hcdf.lock").exists()


def test_extension_content_failing_its_registered_schema_fails_and_writes_nothing(cli, published, tmp_path):
    doc = _robot(tmp_path, extension=_ros2(BAD_TOPIC))
    flat = tmp_path / "flat.hcdf"
    res = _resolve(cli, published, doc, "--out", flat)
    assert res.exit_code == 1
    (err,) = res.json["errors"]
    assert err["code"] == "extension-content" and "warp_speed" in err["message"] and err["line"] == 4
    assert "org.ros2 1.0" in err["message"]
    assert not (tmp_path / "robot.hcdf.lock").exists() and not flat.exists()


def test_stream_profile_with_another_digest_than_registered_exits_1_and_writes_nothing(cli, published, tmp_path):
    changed = PROFILE.read_bytes().replace(b'max-latency-us="200"', b'max-latency-us="900"', 1)
    assert changed != PROFILE.read_bytes()
    doc = _robot(tmp_path, profile=changed)
    flat = tmp_path / "flat.hcdf"
    res = _resolve(cli, published, doc, "--out", flat)
    assert res.exit_code == 1, res.stdout
    (err,) = res.json["errors"]
    assert err["code"] == "stream-profile-digest" and err["line"] == 5
    assert "profiles/op.streams.xml (operational 1.0) differs from the one registered" in err["message"]
    registered = hashlib.sha256(PROFILE.read_bytes()).hexdigest()
    assert err["expected"] == f"sha256:{registered} ({len(PROFILE.read_bytes())} bytes)"
    assert err["actual"] == f"sha256:{hashlib.sha256(changed).hexdigest()} ({len(changed)} bytes)"
    assert not (tmp_path / "robot.hcdf.lock").exists() and not flat.exists()
    # the same tree without --registry resolves: the error is the registry's
    assert cli("resolve", doc).exit_code == 0


def test_a_profile_with_an_unregistered_name_is_not_checked(cli, published, tmp_path):
    other = PROFILE.read_bytes().replace(b'name="operational"', b'name="lab-bench"', 1)
    doc = _robot(tmp_path, profile=other)
    res = _resolve(cli, published, doc)
    assert res.exit_code == 0, res.stdout
    assert res.json["errors"] == []


def test_remote_profile_is_checked_from_the_cache(cli, published, tmp_path, https_server, tls):
    changed = PROFILE.read_bytes().replace(b'max-latency-us="200"', b'max-latency-us="900"', 1)
    url = https_server.add("/op.streams.xml", changed)
    doc = tmp_path / "robot.hcdf"
    doc.write_text(f'<hcdf version="1.0"><network name="n">\n<stream-profile uri="{url}"/></network></hcdf>\n')
    res = _resolve(cli, published, doc, "--ca-bundle", tls.ca_pem)
    assert res.exit_code == 1, res.stdout
    assert [e["code"] for e in res.json["errors"]] == ["stream-profile-digest"]
    assert res.json["errors"][0]["url"] == url


def test_verify_checks_against_a_folder_registry_and_writes_nothing(cli, published, tmp_path, monkeypatch):
    reg, _ = published
    changed = PROFILE.read_bytes().replace(b'max-latency-us="200"', b'max-latency-us="900"', 1)
    doc = _robot(tmp_path / "bad", profile=changed)
    good = _robot(tmp_path / "good", extension=_ros2())
    cache = tmp_path / "xdg"
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    assert cli("resolve", doc).exit_code == 0 and cli("resolve", good).exit_code == 0
    registry_cache = cache / "hcdf-trust" / "registry"
    assert not registry_cache.exists()
    ok = cli("verify", good, "--registry", reg.site, "--trusted-root", reg.root_json, "--json")
    assert ok.exit_code == 0, ok.stdout
    res = cli("verify", doc, "--registry", reg.site, "--trusted-root", reg.root_json, "--json")
    assert res.exit_code == 1
    assert [e["code"] for e in res.json["errors"]] == ["stream-profile-digest"]
    assert not registry_cache.exists()  # verify writes nothing, not even the TUF client's state


def test_verify_keeps_the_rollback_protection_of_the_client_cache(cli, published, tmp_path):
    """verify's temporary client starts from what resolve's client trusted: a site that
    went back to an older timestamp is a rollback, although verify never updates that state."""
    from tuf.api.metadata import Metadata

    reg, _ = published
    site = tmp_path / "site"
    shutil.copytree(reg.site, site)
    doc = _robot(tmp_path / "r", extension=_ros2())
    args = ["--registry", site, "--trusted-root", reg.root_json]
    assert cli("resolve", doc, *args).exit_code == 0
    timestamp = site / "metadata" / "timestamp.json"
    old = timestamp.read_bytes()
    ts = Metadata.from_bytes(old)
    ts.signed.version += 1  # a newer publication: the timestamp moves on
    ts.signatures.clear()
    ts.sign(reg.top_signer("timestamp"))
    timestamp.write_bytes(ts.to_bytes())
    assert cli("resolve", doc, *args).exit_code == 0
    assert cli("verify", doc, *args).exit_code == 0
    timestamp.write_bytes(old)  # the mirror goes back
    res = cli("verify", doc, *args)
    assert res.exit_code == 1 and "rollback attack" in res.stderr, res.stderr


def test_registry_needs_a_trusted_root_and_the_other_way_round(cli, published, tmp_path):
    reg, srv = published
    doc = _robot(tmp_path)
    res = cli("resolve", doc, "--registry", srv.base)
    assert res.exit_code == 2 and "--registry needs --trusted-root" in res.stderr
    res = cli("resolve", doc, "--trusted-root", reg.root_json)
    assert res.exit_code == 2 and "--trusted-root goes with --registry" in res.stderr
    res = cli("verify", doc, "--registry", reg.site)
    assert res.exit_code == 2 and "--trusted-root" in res.stderr
    assert not (tmp_path / "robot.hcdf.lock").exists()


def test_offline_runs_take_only_a_folder_registry(cli, published, tmp_path):
    reg, srv = published
    doc = _robot(tmp_path)
    for verb in (["resolve", doc, "--offline"], ["verify", doc]):
        res = cli(*verb, "--registry", srv.base, "--trusted-root", reg.root_json)
        assert res.exit_code == 2 and "is a URL, and this run is offline" in res.stderr, verb
    res = cli("resolve", doc, "--offline", "--registry", reg.site, "--trusted-root", reg.root_json)
    assert res.exit_code == 0, res.stderr


def test_missing_trusted_root_or_site_is_an_input_error_before_resolving(cli, published, tmp_path):
    reg, srv = published
    doc = _robot(tmp_path)
    res = cli("resolve", doc, "--registry", srv.base, "--trusted-root", tmp_path / "nope.json")
    assert res.exit_code == 3 and "nope.json" in res.stderr
    res = cli("resolve", doc, "--registry", tmp_path / "no-site", "--trusted-root", reg.root_json)
    assert res.exit_code == 3 and "no such registry site folder" in res.stderr
    assert not (tmp_path / "robot.hcdf.lock").exists()


def test_outputs_may_not_replace_the_trusted_root(cli, published, tmp_path):
    reg, srv = published
    doc = _robot(tmp_path)
    root = tmp_path / "root.json"
    shutil.copy(reg.root_json, root)
    res = cli("resolve", doc, "--registry", srv.base, "--trusted-root", root, "--out", root)
    assert res.exit_code == 3 and "trusted root" in res.stderr
    assert root.read_bytes() == reg.root_json.read_bytes()


def test_a_tampered_registry_is_an_attack(cli, published, tmp_path):
    """The registry check goes through TUF: a site whose target was swapped is refused (exit 1)."""
    reg, _ = published
    site = tmp_path / "site"
    shutil.copytree(reg.site, site)
    (schema,) = (site / "targets" / "extensions" / "org.ros2").glob("*.1.0.xsd")
    schema.write_bytes(schema.read_bytes().replace(b"sensor_data", b"sensor_datX", 1))
    doc = _robot(tmp_path / "r", extension=_ros2())
    res = cli("resolve", doc, "--registry", site, "--trusted-root", reg.root_json)
    assert res.exit_code == 1 and "arbitrary content" in res.stderr
    assert not (tmp_path / "r" / "robot.hcdf.lock").exists()


def test_verify_of_a_bundle_checks_its_stream_profile_entry_against_the_registry(cli, published, tmp_path):
    """The registry check reads the profile again after resolution: from the bundle, not a file."""
    reg, _ = published
    changed = PROFILE.read_bytes().replace(b'max-latency-us="200"', b'max-latency-us="900"', 1)
    registry = ("--registry", reg.site, "--trusted-root", reg.root_json, "--json")
    for name, profile, code in (("good", None, 0), ("bad", changed, 1)):
        doc = _robot(tmp_path / name, profile=profile)
        out = tmp_path / f"{name}.hcdfz"
        assert cli("bundle", doc, out).exit_code == 0
        shutil.rmtree(tmp_path / name)  # nothing left to read but the bundle
        res = cli("verify", out, *registry)
        assert res.exit_code == code, res.stdout
        if code:
            assert [e["code"] for e in res.json["errors"]] == ["stream-profile-digest"]
            assert f"{name}.hcdfz/assets/op.streams_" in res.json["errors"][0]["url"]


def test_an_https_registry_is_trusted_through_resolves_ca_bundle(cli, published, tmp_path, serve, tls, monkeypatch):
    """resolve's --ca-bundle means for --registry what it means for every other https fetch."""
    monkeypatch.delenv("HCDF_TRUST_CA_BUNDLE", raising=False)
    reg, _ = published
    site = serve("good", root=reg.site)
    doc = _robot(tmp_path, extension=_ros2())
    r = _resolve(cli, published, doc, "--ca-bundle", tls.ca_pem, site=site.url("/"))
    assert r.exit_code == 0, r.stderr
    (tmp_path / "robot.hcdf.lock").unlink()
    r = _resolve(cli, published, doc, site=site.url("/"))
    assert r.exit_code == 3 and "CERTIFICATE_VERIFY_FAILED" in r.json["errors"][0]["message"], r.stdout


def test_resolve_registry_fetches_stop_after_resolves_timeout(cli, published, tmp_path, http_server):
    """--timeout bounds the registry's fetches too (its client kept its own 30 s default)."""
    import time

    reg, _ = published
    for name in ("2.root.json", "timestamp.json"):
        http_server.stall(f"/metadata/{name}")  # the first request of a TUF refresh: never answered
    doc = _robot(tmp_path)
    start = time.monotonic()
    res = cli(
        "resolve", doc, "--registry", http_server.base, "--trusted-root", reg.root_json, "--json", "--timeout", "1"
    )
    elapsed = time.monotonic() - start
    assert res.exit_code == 3, res.stdout
    assert "timed out" in res.stdout.lower() or "timeout" in res.stdout.lower(), res.stdout
    assert elapsed < 20, elapsed  # 30 s (the client's default) per request without the fix
