"""Registry authentication for ``ota push``/``pull``: anonymous, Basic (htpasswd, the real
registry), bearer token; credentials from the environment, the Docker config file or a
credential helper, never the command line, never in a message or ``--json``; TLS."""

from __future__ import annotations

import base64
import json
import os
import stat

import pytest

from hcdf_trust.oci.client import RegistryClient
from hcdf_trust.oci.reference import parse_reference
from tests._oci import PASSWORD, USER, TokenFront, auth_registry, registry, start_registry, stop_registry  # noqa: F401
from tests._ota import make_robot, tree

pytestmark = pytest.mark.filterwarnings("ignore::ResourceWarning")
B64 = base64.b64encode(f"{USER}:{PASSWORD}".encode()).decode()


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    from tests._oci import module_cli

    cli = module_cli()
    tmp = tmp_path_factory.mktemp("release")
    robot = make_robot(tmp, cli)
    assert robot.build(cli, tmp / "r1").exit_code == 0
    return robot, tmp / "r1"


@pytest.fixture(autouse=True)
def _no_ambient_credentials(monkeypatch, tmp_path):
    for name in ("HCDF_TRUST_OCI_USERNAME", "HCDF_TRUST_OCI_PASSWORD", "HCDF_TRUST_OCI_REGISTRY"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("DOCKER_CONFIG", str(tmp_path / "docker-none"))


def _secret_free(r):
    for text in (r.stdout, r.stderr):
        assert PASSWORD not in text and B64 not in text, text


def _env(monkeypatch, user=USER, password=PASSWORD):
    monkeypatch.setenv("HCDF_TRUST_OCI_USERNAME", user)
    monkeypatch.setenv("HCDF_TRUST_OCI_PASSWORD", password)


def test_anonymous_against_htpasswd_is_refused(cli, auth_registry, release):  # noqa: F811
    robot, rel = release
    r = cli("ota", "push", rel, auth_registry.ref(tag="anon"))
    assert r.exit_code == 3, r.stderr
    assert "(none were found)" in r.stderr


def test_basic_from_the_environment_push_and_pull(cli, auth_registry, release, monkeypatch, tmp_path):  # noqa: F811
    robot, rel = release
    _env(monkeypatch)
    r = cli("ota", "push", rel, auth_registry.ref(tag="env"), "--json")
    assert r.exit_code == 0, r.stderr
    _secret_free(r)
    r = cli("ota", "pull", auth_registry.ref(tag="env"), "--key", robot.pub, "--out", tmp_path / "o", "--json")
    assert r.exit_code == 0, r.stderr
    _secret_free(r)
    assert tree(tmp_path / "o") == tree(rel)


@pytest.mark.parametrize("as_json", [False, True])
def test_wrong_password_never_printed(cli, auth_registry, release, monkeypatch, tmp_path, as_json):  # noqa: F811
    robot, rel = release
    wrong = "Wr0ng-" + PASSWORD
    _env(monkeypatch, password=wrong)
    args = ["--json"] if as_json else []
    r = cli("ota", "pull", auth_registry.ref(tag="env"), "--key", robot.pub, "--out", tmp_path / "o", *args)
    assert r.exit_code == 3, r.stderr
    assert "the credentials were refused" in (r.stdout if as_json else r.stderr)
    for text in (r.stdout, r.stderr):
        assert wrong not in text and base64.b64encode(f"{USER}:{wrong}".encode()).decode() not in text
    assert not (tmp_path / "o").exists()


def test_environment_credentials_go_only_to_the_named_registry(cli, auth_registry, release, monkeypatch):  # noqa: F811
    robot, rel = release
    _env(monkeypatch)
    monkeypatch.setenv("HCDF_TRUST_OCI_REGISTRY", "registry.example.invalid")
    r = cli("ota", "push", rel, auth_registry.ref(tag="scoped"))
    assert r.exit_code == 3 and "none were found" in r.stderr, r.stderr
    monkeypatch.setenv("HCDF_TRUST_OCI_REGISTRY", auth_registry.netloc)
    assert cli("ota", "push", rel, auth_registry.ref(tag="scoped")).exit_code == 0


def test_docker_config_auths(cli, auth_registry, release, monkeypatch, tmp_path):  # noqa: F811
    robot, rel = release
    folder = tmp_path / "docker"
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps({"auths": {auth_registry.netloc: {"auth": B64}}}))
    (folder / "config.json").chmod(0o600)  # as docker login writes it
    monkeypatch.setenv("DOCKER_CONFIG", str(folder))
    r = cli("ota", "push", rel, auth_registry.ref(tag="cfg"), "--json")
    assert r.exit_code == 0, r.stderr
    _secret_free(r)


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o620, 0o602])
@pytest.mark.parametrize("entry", [{"auth": B64}, {"username": USER, "password": PASSWORD}, {"identitytoken": "tok"}])
def test_docker_config_holding_credentials_readable_by_others_is_refused(
    cli,
    auth_registry,  # noqa: F811
    release,
    monkeypatch,
    tmp_path,
    mode,
    entry,
):
    """ssh's rule for a key file: a password others can read is no longer a secret (refused
    whichever registry it is for), and a config others can write is not ours."""
    robot, rel = release
    folder = tmp_path / "docker"
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps({"auths": {"other.example": entry}}))
    (folder / "config.json").chmod(mode)
    monkeypatch.setenv("DOCKER_CONFIG", str(folder))
    r = cli("ota", "push", rel, auth_registry.ref(tag="cfg"), "--json")
    assert r.exit_code == 3, r.stderr
    (err,) = r.json["errors"]
    assert err["code"] == "secret" and "chmod 600" in err["message"], err
    _secret_free(r)
    r = cli("ota", "pull", auth_registry.ref(tag="cfg"), "--key", robot.pub, "--out", tmp_path / "o")
    assert r.exit_code == 3 and f"permissions 0{mode:o} are too open" in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("mode,ok", [(0o644, True), (0o620, False)])
def test_docker_config_without_credentials_may_be_readable_not_writable(
    cli,
    registry,  # noqa: F811
    release,
    monkeypatch,
    tmp_path,
    mode,
    ok,
):
    robot, rel = release
    folder = tmp_path / "docker"
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps({"auths": {}, "credHelpers": {"other.example": "x"}}))
    (folder / "config.json").chmod(mode)
    monkeypatch.setenv("DOCKER_CONFIG", str(folder))
    r = cli("ota", "push", rel, registry.ref(tag="readable"))
    assert (r.exit_code == 0) is ok, r.stderr
    if not ok:
        assert "must be writable by its owner only" in r.stderr, r.stderr


def test_docker_config_with_duplicate_keys_is_refused(cli, auth_registry, release, monkeypatch, tmp_path):  # noqa: F811
    robot, rel = release
    folder = tmp_path / "docker"
    folder.mkdir()
    (folder / "config.json").write_text('{"auths": {}, "auths": {}}')
    monkeypatch.setenv("DOCKER_CONFIG", str(folder))
    r = cli("ota", "push", rel, auth_registry.ref(tag="cfg"))
    assert r.exit_code == 3 and "appears twice" in r.stderr, r.stderr


def test_credential_helper(cli, auth_registry, release, monkeypatch, tmp_path):  # noqa: F811
    robot, rel = release
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    helper = bin_dir / "docker-credential-hcdftest"
    helper.write_text(
        "#!/bin/sh\n"
        f'read host; [ "$1" = get ] && [ "$host" = "{auth_registry.netloc}" ] || exit 1\n'
        f"echo '{json.dumps({'ServerURL': auth_registry.netloc, 'Username': USER, 'Secret': PASSWORD})}'\n"
    )
    helper.chmod(stat.S_IRWXU)
    folder = tmp_path / "docker"
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps({"credHelpers": {auth_registry.netloc: "hcdftest"}}))
    monkeypatch.setenv("DOCKER_CONFIG", str(folder))
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    r = cli("ota", "push", rel, auth_registry.ref(tag="helper"), "--json")
    assert r.exit_code == 0, r.stderr
    _secret_free(r)


def test_bearer_token(cli, registry, release, monkeypatch, tmp_path):  # noqa: F811
    robot, rel = release
    front = TokenFront(registry, USER, PASSWORD)
    try:
        r = cli("ota", "push", rel, front.ref(tag="bearer"))
        assert r.exit_code == 3 and "none were found" in r.stderr, r.stderr
        _env(monkeypatch)
        r = cli("ota", "push", rel, front.ref(tag="bearer"), "--json")
        assert r.exit_code == 0, r.stderr
        r = cli("ota", "pull", front.ref(tag="bearer"), "--key", robot.pub, "--out", tmp_path / "o", "--json")
        assert r.exit_code == 0, r.stderr
        for text in (r.stdout, r.stderr):
            assert front.token not in text
        _secret_free(r)
        assert tree(tmp_path / "o") == tree(rel)
        # the password went to the token realm only, never to a registry endpoint
        assert f"Basic {B64}" in front.seen_auth
    finally:
        front.close()


@pytest.mark.parametrize(
    "target",
    [
        f"oci://{USER}:{PASSWORD}@127.0.0.1:5000/robots/scout:r1",
        f"oci://127.0.0.1:5000/robots/scout:r1?password={PASSWORD}",
    ],
)
def test_credentials_on_the_command_line_are_refused(cli, release, target, tmp_path):
    robot, _ = release
    for args in (["--json"], []):
        r = cli("ota", "pull", target, "--key", robot.pub, "--out", tmp_path / "o", *args)
        assert r.exit_code == 3, r.stderr
        _secret_free(r)


def test_plain_http_only_for_loopback_or_insecure_registry():
    def scheme(text, **kw):
        return RegistryClient(parse_reference(text), **kw).scheme

    assert scheme("oci://127.0.0.1:5000/a:b") == "http"
    assert scheme("oci://localhost/a:b") == "http"
    assert scheme("oci://[::1]:5000/a:b") == "http"
    assert scheme("oci://registry.example.com/a:b") == "https"
    assert scheme("oci://10.0.0.1:5000/a:b") == "https"
    assert scheme("oci://10.0.0.1:5000/a:b", insecure_registries=["10.0.0.1:5000"]) == "http"
    client = RegistryClient(parse_reference("oci://127.0.0.1:5000/a:b"))
    assert not client._allowed_scheme("http://10.0.0.1/x")
    assert client._allowed_scheme("https://10.0.0.1/x")


def test_tls_registry_with_ca_bundle(cli, release, tls, tmp_path_factory, tmp_path):
    """distribution serving TLS with a test CA's certificate: trusted through --ca-bundle only."""
    robot, rel = release
    folder = tmp_path_factory.mktemp("registry-tls")
    cert = tls.ca.issue_cert("127.0.0.1")
    cert.cert_chain_pems[0].write_to_path(str(folder / "cert.pem"))
    cert.private_key_pem.write_to_path(str(folder / "key.pem"))
    reg = start_registry(folder, tls=(folder / "cert.pem", folder / "key.pem"))
    try:
        ref = reg.ref(tag="tls")
        r = cli("ota", "push", rel, ref, "--ca-bundle", tls.ca_pem)
        assert r.exit_code == 0, r.stderr
        r = cli("ota", "pull", ref, "--key", robot.pub, "--out", tmp_path / "o", "--ca-bundle", tls.ca_pem)
        assert r.exit_code == 0, r.stderr
        other = tmp_path / "other-ca.pem"
        tls.other_ca.cert_pem.write_to_path(str(other))
        r = cli("ota", "pull", ref, "--key", robot.pub, "--out", tmp_path / "o2", "--ca-bundle", other)
        assert r.exit_code == 3 and "CERTIFICATE_VERIFY_FAILED" in r.stderr, r.stderr
        assert not (tmp_path / "o2").exists()
    finally:
        stop_registry(reg)


def test_a_registry_echoing_the_password_is_not_shown(cli, release, http_server, monkeypatch, tmp_path):
    """A hostile registry that knows the password (Basic sends it) puts it into a redirect."""
    robot, rel = release
    _env(monkeypatch)
    http_server.redirect("/v2/", f"http://127.0.0.2:9/leak/{PASSWORD}/{B64}")
    for args in ([], ["--json"]):
        r = cli("ota", "push", rel, f"oci://127.0.0.1:{http_server.port}/a/b:c", *args)
        assert r.exit_code == 3, r.stderr
        assert "redirect" in r.stderr + r.stdout
        _secret_free(r)


def test_no_credentials_over_plain_http_to_another_machine(monkeypatch):
    """--insecure-registry allows plain http, but never a password in clear over the network."""
    import pytest as _pytest

    from hcdf_trust.oci.auth import Credentials
    from hcdf_trust.oci.client import RegistryAuthError

    client = RegistryClient(
        parse_reference("oci://10.0.0.1:5000/a:b"),
        credentials=Credentials(USER, PASSWORD),
        insecure_registries=["10.0.0.1:5000"],
    )
    with _pytest.raises(RegistryAuthError, match="refusing to send credentials over plain http"):
        client._answer('Basic realm="x"', "http://10.0.0.1:5000/v2/")
    with _pytest.raises(RegistryAuthError, match="refusing to send credentials over plain http"):
        client._answer('Bearer realm="https://auth.example/token"', "http://10.0.0.1:5000/v2/")
    loop = RegistryClient(parse_reference("oci://127.0.0.1:5000/a:b"), credentials=Credentials(USER, PASSWORD))

    def no_network(*a, **k):
        raise AssertionError("the credentials were about to be sent")

    monkeypatch.setattr(loop._client, "get", no_network)
    monkeypatch.setattr(loop._client, "post", no_network)
    with _pytest.raises(RegistryAuthError, match="token realm http://10.0.0.2/token is not https"):
        loop._answer('Bearer realm="http://10.0.0.2/token"', "http://127.0.0.1:5000/v2/")


def test_an_endless_token_answer_is_refused(http_server, monkeypatch):
    """A token realm that answers without end: refused at 1 MiB, not read into memory."""
    from hcdf_trust.oci.auth import Credentials
    from hcdf_trust.oci.client import RegistryError

    http_server.stream("/token", 1 << 40, chunked=True)
    client = RegistryClient(
        parse_reference(f"oci://127.0.0.1:{http_server.port}/a:b"), credentials=Credentials(USER, PASSWORD)
    )
    with pytest.raises(RegistryError, match="longer than the 1048576-byte limit"):
        client._answer(f'Bearer realm="{http_server.url("/token")}"', client.origin + "/v2/")
    client.close()
