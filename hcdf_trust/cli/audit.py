"""``hcdf-trust audit``: one report over the whole include tree. Parses, calls, renders."""

from __future__ import annotations

import functools
import sys
from datetime import datetime
from typing import Any

import click

from ..errors import counted
from . import INSECURE_REGISTRY_OPTION, emit_json, handle_errors, say, tree_options
from .macsec import store_options
from .params import ConfigOption, from_config, project_config


@click.command(name="audit")
@click.argument("doc", type=click.Path(dir_okay=False))
@click.option(
    "--policy",
    "policy_file",
    cls=ConfigOption,
    config_key="audit.policy",
    type=click.Path(dir_okay=False),
    help="Audit policy (TOML) [default: built-in].",
)
@tree_options
@click.option("--release", "release_dir", type=click.Path(file_okay=False), help="Signed OTA release folder.")
@click.option("--key", "release_key", type=click.Path(dir_okay=False), help="The release's public key (PEM).")
@click.option(
    "--fleet-report",
    type=click.Path(dir_okay=False),
    help="A signed report written by `hcdf-trust fleet status`: flag comps not running the release.",
)
@click.option("--fleet-key", type=click.Path(dir_okay=False), help="The host's public key (PEM) that signed it.")
@click.option(
    "--registry",
    "registry_site",
    cls=ConfigOption,
    config_key="registry.site",
    help="Registry (https URL, oci:// artifact or folder): extension domains and schemas.",
)
@click.option(
    "--trusted-root",
    cls=ConfigOption,
    config_key="registry.trusted-root",
    type=click.Path(dir_okay=False),
    help="The registry's root.json you trust.",
)
@INSECURE_REGISTRY_OPTION  # --ca-bundle comes with tree_options: --online fetches and the --registry
@functools.partial(store_options, required=False)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout (shape: docs/audit.md).")
@handle_errors
def audit_cmd(
    doc: str,
    policy_file: str | None,
    tree: Any,
    release_dir: str | None,
    release_key: str | None,
    fleet_report: str | None,
    fleet_key: str | None,
    registry_site: str | None,
    trusted_root: str | None,
    insecure_registries: tuple[str, ...],
    store_dir: str | None,
    passphrase_file: str | None,
    now_given: datetime | None,
    as_json: bool,
    **backend: Any,
) -> None:
    """Audit DOC's supply chain: references, firmware, MACsec, extensions.

    Every finding has a severity, a code, a file and a line. Exits 1 when a finding is at or
    above the policy's threshold, 3 when an input cannot be read.
    """
    from ..audit import AuditOptions
    from ..audit import audit as run
    from ..audit.policy import DEFAULT, load

    if (release_dir is None) != (release_key is None):
        raise click.UsageError("--release and --key go together")
    if (fleet_report is None) != (fleet_key is None):
        raise click.UsageError("--fleet-report and --fleet-key go together")
    if registry_site is not None and trusted_root is None:
        raise click.UsageError("--registry needs --trusted-root")
    if registry_site is not None and "://" in registry_site and tree.offline:
        if from_config("registry_site"):
            raise click.UsageError(
                f"registry.site of {project_config().shown} is on the network: add --online, or --no-project-config"
            )
        raise click.UsageError(f"--registry {registry_site} is on the network: add --online (or give a folder)")
    if store_dir is None and (passphrase_file or now_given or any(backend.values())):
        raise click.UsageError("the key store options need --store")
    policy = load(policy_file) if policy_file is not None else DEFAULT
    wrapper = now = schemas = None
    if store_dir is not None:
        from .macsec import _now, _wrapper

        now = _now(now_given)
        wrapper = _wrapper(passphrase_file, backend)
    if registry_site is not None:
        from ..registry.validation import RegistrySchemaSource
        from .registry import _client

        assert trusted_root is not None
        schemas = RegistrySchemaSource(
            _client(
                registry_site, trusted_root, None, ca_bundle=tree.ca_bundle, insecure_registries=insecure_registries
            )
        )
    report = run(
        doc,
        AuditOptions(
            policy=policy,
            tree=tree,
            release_dir=release_dir,
            release_key=release_key,
            fleet_report=fleet_report,
            fleet_key=fleet_key,
            store_dir=store_dir,
            store_wrapper=wrapper,
            now=now,
            registry=schemas,
        ),
    )
    if as_json:
        emit_json(report.to_dict())
    else:
        for f in report.sorted():
            say(str(f), always=True)
        counts = report.to_dict()["counts"]
        say(
            f"audit: {counted(counts['error'], 'error')}, {counted(counts['warning'], 'warning')}, "
            f"{counts['info']} info "
            f"({', '.join(report.checked)}); {len(report.failing)} at or above {policy.threshold}",
        )
    sys.exit(0 if report.ok else 1)
