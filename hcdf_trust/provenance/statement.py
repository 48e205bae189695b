"""The in-toto Statement v1 of a release, with a SLSA Provenance v1 predicate.

Everything in it comes from the build's inputs and the environment, never from the
clock or the machine, so two builds of the same inputs with the same
``SOURCE_DATE_EPOCH`` (and CI variables) give byte-identical statements:

- ``subject``: every file of the release folder, by relative path and SHA-256.
- ``externalParameters``: what the person or CI chose (the root document's name, the
  images built, the base URL, the ota.toml name). Digests are inputs, not parameters:
  they are in ``resolvedDependencies`` (SLSA v1).
- ``resolvedDependencies``: the root document, the lock, every artifact the lock lists
  (includes, models, firmware manifests) with the lock's own URL and SHA-256, every
  binary an image was built from (``hcdf-firmware:board/app``, its path under
  ``--firmware-dir``) and ota.toml.
- ``runDetails``: ``--builder-id`` (else the CI's workflow, else ours), the CI run as
  ``invocationId``, and the release date as ``startedOn``/``finishedOn``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from . import BUILD_TYPE, DEFAULT_BUILDER_ID, PREDICATE_TYPE, STATEMENT_TYPE

EXTERNAL_PARAMETERS = frozenset({"root", "images", "baseUrl", "otaConfig"})
LOCK_DEPENDENCY = "hcdf-lock"  # resolvedDependencies[].name of the lock
ROOT_DEPENDENCY = "hcdf-root"  # ... and of the root document
FIRMWARE_DEPENDENCY = "hcdf-firmware:"  # ... and, + "board/app", of the binary an image was built from


@dataclass(frozen=True)
class Dependency:
    """One ``resolvedDependencies`` entry: an input of the build, by name, SHA-256 and,
    optionally, how the build spelled it (``uri``).

    >>> from hcdf_trust.provenance.build import Dependency
    >>> Dependency("hcdf-lock", "ab" * 32, "robot.hcdf.lock").to_json()["uri"]
    'robot.hcdf.lock'
    """

    name: str
    sha256: str
    uri: str | None = None

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "digest": {"sha256": self.sha256}}
        if self.uri is not None:
            out["uri"] = self.uri
        return out


@dataclass(frozen=True)
class BuildFacts:
    """What the statement of a release says, gathered by ``ota build``."""

    files: dict[str, str]  # release-relative path -> SHA-256 (every file of the folder)
    root: str
    root_sha256: str
    lock_sha256: str
    lock: str  # the lock file's name
    images: tuple[str, ...]  # "board/app"
    dependencies: tuple[Dependency, ...]  # besides the root and the lock (firmware inputs included)
    date: str
    base_url: str | None = None
    ota_config: str | None = None
    builder_id: str | None = None


def release_statement(facts: BuildFacts, env: dict[str, str] | None = None) -> dict[str, Any]:
    """The Statement of a release (build type :data:`BUILD_TYPE`) as a JSON object."""
    params: dict[str, Any] = {"root": facts.root, "images": sorted(facts.images)}
    if facts.base_url is not None:
        params["baseUrl"] = facts.base_url
    if facts.ota_config is not None:
        params["otaConfig"] = facts.ota_config
    deps = [
        Dependency(ROOT_DEPENDENCY, facts.root_sha256, facts.root),
        Dependency(LOCK_DEPENDENCY, facts.lock_sha256, facts.lock),
        *sorted(facts.dependencies, key=lambda d: (d.name, d.uri or "", d.sha256)),
    ]
    return statement(
        facts.files, parameters=params, dependencies=deps, date=facts.date, builder_id=facts.builder_id, env=env
    )


def statement(
    subjects: Mapping[str, str],
    *,
    parameters: Mapping[str, Any],
    dependencies: Sequence[Dependency],
    date: str,
    build_type: str = BUILD_TYPE,
    builder_id: str | None = None,
    env: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """An in-toto Statement v1 with a SLSA Provenance v1 predicate, as a JSON object (see
    :func:`serialize` for its bytes): ``subjects`` (name -> SHA-256) sorted by name,
    ``dependencies`` in the order given, ``date`` (RFC 3339) as start and finish."""
    env = os.environ if env is None else env
    ci_builder, invocation = _ci(env)
    metadata: dict[str, Any] = {"startedOn": date, "finishedOn": date}
    if invocation is not None:
        metadata["invocationId"] = invocation
    return {
        "_type": STATEMENT_TYPE,
        "subject": [{"name": name, "digest": {"sha256": sha}} for name, sha in sorted(subjects.items())],
        "predicateType": PREDICATE_TYPE,
        "predicate": {
            "buildDefinition": {
                "buildType": build_type,
                "externalParameters": dict(parameters),
                "resolvedDependencies": [d.to_json() for d in dependencies],
            },
            "runDetails": {
                "builder": {"id": builder_id or ci_builder or DEFAULT_BUILDER_ID},
                "metadata": metadata,
            },
        },
    }


def serialize(doc: dict[str, Any]) -> bytes:
    """The one serialization that is signed and published: compact, sorted keys, UTF-8."""
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()


def _ci(env: Mapping[str, str]) -> tuple[str | None, str | None]:
    """GitHub Actions' workflow (builder) and run (invocation), when the build runs there."""
    server, repo, run = env.get("GITHUB_SERVER_URL"), env.get("GITHUB_REPOSITORY"), env.get("GITHUB_RUN_ID")
    if not (server and repo and run):
        return None, None
    workflow = env.get("GITHUB_WORKFLOW_REF")
    attempt = env.get("GITHUB_RUN_ATTEMPT", "1")
    builder = f"{server}/{workflow}" if workflow else None
    return builder, f"{server}/{repo}/actions/runs/{run}/attempts/{attempt}"
