"""``hcdf-trust registry …``: parse, call :mod:`hcdf_trust.registry`, render. No logic here.

tuf and securesystemslib are imported inside the commands, so ``hcdf-trust --help`` stays fast.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any

import click

from ..errors import counted
from ..outputs import OutputPlan
from . import CA_BUNDLE_OPTION, INSECURE_REGISTRY_OPTION, JSON_OPTION, emit_json, handle_errors, say
from .params import TIMEOUT, Duration

passphrase_option = click.option(
    "--passphrase-file",
    type=click.Path(dir_okay=False),
    help="File holding the keys' passphrase (the whole file minus one final newline, mode 0600) "
    "[default: $HCDF_TRUST_PASSPHRASE].",
)


def _ring(keys: tuple[str, ...], passphrase_file: str | None) -> Any:
    """The private keys in the ``--keys`` folders; the passphrase is read when a key is first needed."""
    from ..registry.keys import KeyRing, read_passphrase

    return KeyRing(keys, lambda: read_passphrase(passphrase_file))


def _plan(passphrase_file: str | None) -> OutputPlan:
    """The run's OutputPlan, with the passphrase file (an input of every verb that signs) protected."""
    plan = OutputPlan()
    if passphrase_file is not None:
        plan.protect(passphrase_file, what="the passphrase file")
    return plan


sigstore_root_option = click.option(
    "--sigstore-trusted-root",
    "sigstore_root",
    type=click.Path(dir_okay=False),
    help="Sigstore trusted_root.json that bundles are verified against, offline (needs hcdf-trust[sigstore]).",
)


def _identity(identity: str | None, issuer: str | None) -> tuple[str, str] | None:
    if (identity is None) != (issuer is None):
        raise click.UsageError("--sigstore-identity and --sigstore-issuer go together")
    return (identity, issuer) if identity is not None and issuer is not None else None


@click.group()
def registry() -> None:
    """A signed registry (TUF) of extension domains, stream profiles and core schemas."""


@registry.command()
@click.argument("source_dir", metavar="DIR", type=click.Path(file_okay=False))
@click.option(
    "--keys",
    "keydir",
    required=True,
    type=click.Path(file_okay=False),
    help="Folder for the private keys (kept outside DIR).",
)
@passphrase_option
@JSON_OPTION
@handle_errors
def init(source_dir: str, keydir: str, passphrase_file: str | None, as_json: bool) -> None:
    """Start a registry source in DIR: fresh root, targets, snapshot and timestamp keys."""
    from ..registry import edit
    from ..registry.keys import read_passphrase

    plan = _plan(passphrase_file)
    root = edit.init(Path(source_dir), Path(keydir), read_passphrase(passphrase_file), plan=plan)
    plan.commit()
    if as_json:
        roles = {role: t.keyids[0] for role, t in root.roles.items()}
        emit_json({"ok": True, "source": source_dir, "keys": keydir, "roles": roles, "errors": []})
        return
    for role, t in root.roles.items():
        say(f"{role}: key {t.keyids[0]}")
    say(f"wrote {source_dir}/root.toml; private keys (0600) in {keydir}")


@registry.command()
@click.option("--keys", "keydir", required=True, type=click.Path(file_okay=False), help="Folder for the private key.")
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False), help="Public key file to write.")
@click.option("--force", is_flag=True, help="Replace an existing public key file at --out.")
@passphrase_option
@JSON_OPTION
@handle_errors
def keygen(keydir: str, out: str, force: bool, passphrase_file: str | None, as_json: bool) -> None:
    """Make an owner key: the private half in --keys, the public half in --out."""
    from ..registry import edit
    from ..registry.keys import read_passphrase

    plan = _plan(passphrase_file)
    key = edit.keygen(Path(keydir), Path(out), read_passphrase(passphrase_file), plan=plan, force=force)
    plan.commit()
    private = f"{keydir}/{key.keyid}.key"
    if as_json:
        emit_json({"ok": True, "keyid": key.keyid, "public": out, "private": private, "errors": []})
        return
    say(f"key {key.keyid}: public {out}, private {private}")


@registry.command()
@click.argument("source_dir", metavar="DIR", type=click.Path(exists=True, file_okay=False))
@click.option("--domain", help="Extension domain (reverse-DNS, e.g. org.ros2).")
@click.option("--version", "version", help="Version of the domain's schema, or of a --core schema.")
@click.option("--schema", type=click.Path(exists=True, dir_okay=False), help="The schema file (inside --content).")
@click.option("--profile", type=click.Path(exists=True, dir_okay=False), help="A stream profile file (.streams.xml).")
@click.option("--core", help="Register --schema as core schema NAME (hcdf, hcdf-stream-profile).")
@click.option("--owner", help="Owner's name (a new domain).")
@click.option(
    "--owner-key",
    "owner_keys",
    multiple=True,
    type=click.Path(exists=True, dir_okay=False),
    help="Owner's public key file (a new domain; repeatable).",
)
@click.option(
    "--threshold",
    type=click.IntRange(1, 255),
    default=1,
    show_default=True,
    help="Owner signatures a version needs (a new domain).",
)
@click.option("--description", default="", help="One line about the entry (a new entry).")
@click.option(
    "--content",
    "content_dir",
    type=click.Path(exists=True, file_okay=False),
    default=".",
    show_default=True,
    help="Content folder the file lies in (its recorded path is relative to it).",
)
@click.option(
    "--keys",
    "keydirs",
    multiple=True,
    type=click.Path(exists=True, file_okay=False),
    help="Folder holding the owner's private keys (repeatable).",
)
@click.option("--sigstore-identity", help="Owner's sigstore identity (a new domain), e.g. an e-mail or workflow URI.")
@click.option("--sigstore-issuer", help="OIDC issuer of --sigstore-identity (a new domain).")
@click.option(
    "--sigstore-bundle",
    type=click.Path(exists=True, dir_okay=False),
    help="Approve the version with this sigstore bundle over `registry statement` instead of an owner key.",
)
@sigstore_root_option
@passphrase_option
@JSON_OPTION
@handle_errors
def add(
    source_dir: str,
    domain: str | None,
    version: str | None,
    schema: str | None,
    profile: str | None,
    core: str | None,
    owner: str | None,
    owner_keys: tuple[str, ...],
    threshold: int,
    description: str,
    content_dir: str,
    keydirs: tuple[str, ...],
    sigstore_identity: str | None,
    sigstore_issuer: str | None,
    sigstore_bundle: str | None,
    sigstore_root: str | None,
    passphrase_file: str | None,
    as_json: bool,
) -> None:
    """Record a domain version (signed by its owner), a stream profile or a core schema."""
    from ..registry import edit
    from ..registry.source import load_source

    chosen = [x for x in (domain, profile, core) if x]
    if len(chosen) != 1:
        raise click.UsageError("give exactly one of --domain, --profile or --core")
    source = load_source(source_dir)
    plan = _plan(passphrase_file)
    content = Path(content_dir)
    if profile:
        name, ver = edit.profile_identity(profile)
        done: Any = edit.add_artifact(
            source, "profile", name, ver, profile, content_dir=content, plan=plan, description=description
        )
        what = f"stream profile {name} {ver}"
    else:
        if core and (not version or not schema):
            raise click.UsageError("--core needs --version and --schema")
        if core:
            assert version is not None and schema is not None
            done = edit.add_artifact(
                source, "schema", core, version, schema, content_dir=content, plan=plan, description=description
            )
            what = f"core schema {core} {version}"
        else:
            assert domain is not None
            done = edit.add_domain(
                source,
                domain,
                version,
                schema,
                content_dir=content,
                plan=plan,
                ring=_ring(keydirs, passphrase_file),
                owner=owner,
                owner_keys=[edit.read_public_key(k) for k in owner_keys],
                threshold=threshold,
                description=description,
                sigstore=_identity(sigstore_identity, sigstore_issuer),
                bundle=sigstore_bundle,
                sigstore_root=sigstore_root,
            )
            what = f"{domain} {version}" if version else f"domain {domain}"
    if done is not None:
        plan.commit()
    if as_json:
        recorded = str(plan.paths[0]) if done is not None else None
        emit_json({"ok": True, "entry": what, "recorded": recorded, "unchanged": done is None, "errors": []})
    elif done is None:
        say(f"{what}: already registered with the same content")
    else:
        say(f"{what}: recorded in {plan.paths[0]}")


@registry.command()
@click.option("--domain", required=True, help="Extension domain (reverse-DNS).")
@click.option("--version", "version", required=True, help="Version of the domain's schema.")
@click.option("--schema", required=True, type=click.Path(exists=True, dir_okay=False), help="The schema file.")
@click.option(
    "--content",
    "content_dir",
    type=click.Path(exists=True, file_okay=False),
    default=".",
    show_default=True,
    help="Content folder the schema lies in.",
)
@click.option(
    "-o", "--out", required=True, type=click.Path(dir_okay=False), help="Where to write the statement (- for stdout)."
)
@JSON_OPTION
@handle_errors
def statement(domain: str, version: str, schema: str, content_dir: str, out: str, as_json: bool) -> None:
    """Write the bytes an owner signs to approve a version (to sign with `sigstore sign` in CI)."""
    from ..registry import edit

    plan = OutputPlan()
    plan.protect(schema, what="the schema")
    plan.protect_tree(content_dir, what="the content folder")
    if out == "-" and as_json:
        raise click.UsageError("-o - and --json would both write to stdout")
    plan.add(out, edit.statement(domain, version, schema, content_dir=Path(content_dir)), flag="--out", stdout=True)
    plan.commit()
    if as_json:
        emit_json({"ok": True, "domain": domain, "version": version, "wrote": [out], "errors": []})
        return
    if out != "-":
        say(f"statement for {domain} {version} written to {out}")


@registry.command()
@click.argument("source_dir", metavar="DIR", type=click.Path(exists=True, file_okay=False))
@click.option(
    "--role", type=click.Choice(["root", "targets", "snapshot", "timestamp"]), help="Top-level role to give a new key."
)
@click.option("--domain", help="Domain whose owner key to replace (needs its current key in --keys).")
@click.option(
    "--keys",
    "keydirs",
    multiple=True,
    required=True,
    type=click.Path(file_okay=False),
    help="Keys folder; the new private key goes into the first (repeatable).",
)
@passphrase_option
@JSON_OPTION
@handle_errors
def rotate(
    source_dir: str,
    role: str | None,
    domain: str | None,
    keydirs: tuple[str, ...],
    passphrase_file: str | None,
    as_json: bool,
) -> None:
    """Replace a top-level role's key or a domain owner's key; `publish` then signs the change."""
    from ..registry import edit
    from ..registry.keys import read_passphrase
    from ..registry.source import load_source

    if (role is None) == (domain is None):
        raise click.UsageError("give exactly one of --role or --domain")
    source = load_source(source_dir)
    plan = _plan(passphrase_file)
    keydir = Path(keydirs[0])
    passphrase = read_passphrase(passphrase_file)
    if role:
        key = edit.rotate_role(source, role, keydir, passphrase, plan=plan)
    else:
        assert domain is not None
        key = edit.rotate_owner(source, domain, keydir, _ring(keydirs, passphrase_file), passphrase, plan=plan)
    plan.commit()
    if as_json:
        emit_json({"ok": True, "role": role, "domain": domain, "keyid": key.keyid, "errors": []})
        return
    say(f"{role or domain}: new key {key.keyid}; run `registry publish` to sign the change")


@registry.command()
@click.argument("source_dir", metavar="DIR", type=click.Path(exists=True, file_okay=False))
@click.option(
    "--keys",
    "keydirs",
    multiple=True,
    required=True,
    type=click.Path(exists=True, file_okay=False),
    help="Folder of private keys (repeatable: registry keys, owner keys).",
)
@click.option(
    "--content",
    "content_dir",
    required=True,
    type=click.Path(exists=True, file_okay=False),
    help="Folder holding the files the entries name.",
)
@click.option(
    "-o",
    "--out",
    "site",
    required=True,
    type=click.Path(file_okay=False),
    help="Site folder (a previous publication there is continued).",
)
@click.option(
    "--expires",
    "lifetime",
    default="7d",
    show_default=True,
    type=Duration(min=dt.timedelta(minutes=1), max=dt.timedelta(days=3650)),
    help="Timestamp lifetime (30m, 12h, 7d, 2w): clients stop trusting a site not re-published within it.",
)
@sigstore_root_option
@passphrase_option
@click.option(
    "--oci",
    "oci_target",
    metavar="oci://HOST[:PORT]/REPO:TAG",
    help="Also push the site to this OCI registry (one layer per file; credentials as for `ota push`).",
)
@CA_BUNDLE_OPTION
@INSECURE_REGISTRY_OPTION
@JSON_OPTION
@handle_errors
def publish(
    source_dir: str,
    keydirs: tuple[str, ...],
    content_dir: str,
    site: str,
    lifetime: dt.timedelta,
    sigstore_root: str | None,
    passphrase_file: str | None,
    oci_target: str | None,
    ca_bundle: str | None,
    insecure_registries: tuple[str, ...],
    as_json: bool,
) -> None:
    """Write a static TUF repository (consistent snapshots) for DIR into --out (and, with --oci,
    push it to an OCI registry, where `registry verify|fetch oci://…` read it)."""
    from ..registry.publish import publish as do_publish
    from ..registry.source import load_source

    source = load_source(source_dir)
    plan = _plan(passphrase_file)
    plan.protect_tree(source_dir, what="the registry source")
    plan.protect_tree(content_dir, what="the content folder")
    for k in keydirs:
        plan.protect_tree(k, what="a keys folder")
    result = do_publish(
        source,
        _ring(keydirs, passphrase_file),
        Path(content_dir),
        Path(site),
        plan=plan,
        timestamp_lifetime=lifetime,
        sigstore_root=sigstore_root,
    )
    ref = None
    if oci_target is not None:
        from ..oci.reference import parse_reference

        ref = parse_reference(oci_target, need_tag=True)  # refused before anything is written
    plan.commit()
    pushed = None
    if ref is not None:
        from ..oci.client import connect
        from ..oci.site import push_site

        _, client = connect(ref, ca_bundle=ca_bundle, insecure_registries=insecure_registries, push=True)
        with client:
            pushed = push_site(site, ref, client)
    if as_json:
        emit_json(
            {
                "ok": True,
                "versions": result.versions,
                "signed": result.signed,
                "written": [str(p) for p in result.written],
                **({"oci": {"reference": str(ref), **pushed}} if pushed is not None else {}),
                "errors": [],
            }
        )
    else:
        versions = ", ".join(f"{k} v{v}" for k, v in result.versions.items())
        say(f"published {site}: {versions}; {counted(len(result.written), 'file')} written")
        if pushed is not None:
            say(f"pushed {counted(pushed['files'], 'file')} to {ref} ({pushed['digest']})")


def _client(
    site: str,
    trusted_root: str,
    cache_dir: str | None,
    timeout: float = 30.0,
    *,
    ca_bundle: str | None = None,
    insecure_registries: tuple[str, ...] = (),
    flag: str = "--registry",
) -> Any:
    from ..registry.client import RegistryClient

    return RegistryClient.open(
        site,
        trusted_root,
        cache_dir=Path(cache_dir) if cache_dir else None,
        timeout=timeout,
        ca_bundle=ca_bundle,
        insecure_registries=insecure_registries,
        flag=flag,
    )


client_options = [
    click.option(
        "--timeout",
        type=TIMEOUT,
        default=30.0,
        show_default=True,
        help="Seconds to wait for a connection or between bytes (http(s) sites).",
    ),
    click.option(
        "--trusted-root",
        required=True,
        type=click.Path(dir_okay=False),
        help="The root.json you trust (its bytes bootstrap the client).",
    ),
    click.option(
        "--cache-dir",
        type=click.Path(file_okay=False),
        help="Client metadata cache [default: ~/.cache/hcdf-trust/registry/…].",
    ),
    CA_BUNDLE_OPTION,
    INSECURE_REGISTRY_OPTION,
]


def _with_client_options(func: Any) -> Any:
    for option in reversed(client_options):
        func = option(func)
    return func


@registry.command()
@click.argument("site", metavar="SITE_URL|DIR")
@_with_client_options
@JSON_OPTION
@handle_errors
def verify(
    site: str,
    trusted_root: str,
    cache_dir: str | None,
    timeout: float,
    ca_bundle: str | None,
    insecure_registries: tuple[str, ...],
    as_json: bool,
) -> None:
    """Refresh from SITE and check every role and every file it publishes."""
    from ..registry.client import verify as do_verify
    from ..registry.errors import AttackError
    from . import fail

    report = do_verify(
        _client(
            site,
            trusted_root,
            cache_dir,
            timeout,
            ca_bundle=ca_bundle,
            insecure_registries=insecure_registries,
            flag="SITE",
        )
    )
    errors = [
        AttackError(
            f"cross-domain signing: {s.role} lists {s.path}, outside its delegation (ignored by clients)"
            if s.domain
            else f"{s.role} lists {s.path}: only a domain's own role may list its files (it would shadow them)"
        )
        for s in report.stray
    ]
    payload = {"root_version": report.root_version, "roles": report.roles, "targets": report.targets}
    if errors:
        fail(list(errors), as_json=as_json, payload=payload)
    if as_json:
        emit_json({"ok": True, **payload, "errors": []})
    else:
        say(
            f"{site}: verified (root v{report.root_version}, {counted(report.roles, 'domain role')}, "
            f"{counted(report.targets, 'file')})",
        )


@registry.command()
@click.argument(
    "what", nargs=-1, required=True, metavar="DOMAIN[@VERSION] | profile NAME[@VERSION] | schema NAME[@VERSION]"
)
@click.option("--from", "site", required=True, help="Registry site: an http(s) URL or a folder.")
@_with_client_options
@click.option(
    "-o",
    "--out",
    required=True,
    type=click.Path(dir_okay=False),
    help="Where to write the verified file (- for stdout).",
)
@JSON_OPTION
@handle_errors
def fetch(
    what: tuple[str, ...],
    site: str,
    trusted_root: str,
    cache_dir: str | None,
    timeout: float,
    ca_bundle: str | None,
    insecure_registries: tuple[str, ...],
    out: str,
    as_json: bool,
) -> None:
    """Write one verified file from the registry: a domain's schema, a stream profile or a core schema."""
    from ..errors import NotFoundError
    from ..registry.client import latest

    if len(what) == 1:
        kind, spec = "domain", what[0]
    elif len(what) == 2 and what[0] in ("profile", "schema"):
        kind, spec = what
    else:
        raise click.UsageError("give DOMAIN[@VERSION], profile NAME[@VERSION] or schema NAME[@VERSION]")
    name, _, version = spec.partition("@")
    client = _client(
        site,
        trusted_root,
        cache_dir,
        timeout,
        ca_bundle=ca_bundle,
        insecure_registries=insecure_registries,
        flag="SITE",
    )
    if kind == "domain":
        versions = client.versions(name)
    else:
        versions = client.artifacts(kind).get(name, {})
        if not versions:
            raise NotFoundError(f"no {kind} {name} in the registry", url=site)
    if not versions:
        raise NotFoundError(f"{name} has no published version", url=site)
    version = version or latest(versions)
    if version not in versions:
        raise NotFoundError(f"{kind} {name} has no version {version} (has {', '.join(sorted(versions))})", url=site)
    data = client.download(versions[version])
    plan = OutputPlan()
    plan.protect(trusted_root, what="the trusted root")
    plan.protect_tree(client.cache_dir, what="the registry cache")
    if "://" not in site:
        plan.protect_tree(site, what="the registry site")
    if out == "-" and as_json:
        raise click.UsageError("-o - and --json would both write to stdout")
    plan.add(out, data, flag="--out", stdout=True)
    plan.commit()
    if as_json:
        result = {"kind": kind, "name": name, "version": version, "size": len(data), "wrote": [out]}
        emit_json({"ok": True, **result, "errors": []})
        return
    say(f"{name} {version}: {len(data)} bytes verified, written to {'stdout' if out == '-' else out}")


def validate_with_registry(
    doc: str,
    *,
    schema: tuple[str, ...] | str | None,
    site: str,
    trusted_root: str | None,
    strict: bool,
    cache_dir: str | None = None,
    tree: Any = None,
    ca_bundle: str | None = None,
    insecure_registries: tuple[str, ...] = (),
) -> Any:
    """``validate --registry``: the registry supplies the schema (unless ``--schema``) and
    checks extension domains, versions, content and registered stream-profile digests
    (``ca_bundle``, ``insecure_registries``: ``--ca-bundle``, ``--insecure-registry``)."""
    import os

    from ..document import Document, is_json_form
    from ..include.locate import display_path
    from ..registry.validation import RegistrySchemaSource, check_document
    from ..validate import validate_document
    from ..validate.includes import read_local

    if trusted_root is None:
        raise click.UsageError("--registry needs --trusted-root")
    schemas = RegistrySchemaSource(
        _client(site, trusted_root, cache_dir, ca_bundle=ca_bundle, insecure_registries=insecure_registries)
    )
    path = Path(os.path.abspath(doc))
    source = display_path(path)
    data = read_local(path, path.parent, source=source)
    if not schema and is_json_form(data):  # HCDF's JSON form: read through the registry's schema too
        from .. import jsonform

        jsonform.use_schema_provider(schemas.core_xsd)
    report = validate_document(doc, schema=schema or schemas, tree_options=tree)
    parsed = Document.parse(data, source=source)  # held: a JSON document's locations live with it
    tree = parsed.tree
    if tree.getroot().tag == "hcdf":
        report.findings.extend(check_document(tree, source=source, path=path, schemas=schemas, strict=strict))
        report.checked.append("registry")
    return report
