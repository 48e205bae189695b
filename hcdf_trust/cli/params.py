"""One click type per kind of number or time a user gives (a flag or an environment variable),
each range-checked when parsed: a value out of range is a usage error (exit 2) in every verb,
never a traceback or a silent default. Counts use ``click.IntRange`` with both bounds.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from datetime import datetime, timedelta
from typing import Any

import click


class _Clock(click.ParamType[Any]):
    """A :mod:`hcdf_trust.clock` parser as a click type (its ValueError: exit 2, its message)."""

    def parse(self, text: str) -> Any:
        raise NotImplementedError

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if not isinstance(value, str):
            return value  # a default already converted
        try:
            return self.parse(value)
        except ValueError as exc:
            self.fail(str(exc), param, ctx)


class UtcTime(_Clock):
    """``--now``: an ISO 8601 time with a zone, 1970 to 2999."""

    name = "time"

    def parse(self, text: str) -> datetime:
        from ..clock import parse_time

        return parse_time(text)


class EpochTime(_Clock):
    """``SOURCE_DATE_EPOCH``: seconds since 1970, digits only, up to 2999."""

    name = "seconds"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        try:
            return super().convert(value, param, ctx)
        except click.BadParameter as exc:
            source = ctx.get_parameter_source(param.name) if ctx is not None and param and param.name else None
            if source is click.core.ParameterSource.ENVIRONMENT:
                exc.message = f"SOURCE_DATE_EPOCH: {exc.message}"  # type: ignore[misc]  # Final in the stubs
            raise

    def parse(self, text: str) -> datetime:
        from ..clock import parse_epoch

        return parse_epoch(text)


class Duration(_Clock):
    """``--overlap``, ``--expires``: seconds or 30m / 12h / 7d / 2w, from ``min`` to ``max``
    (at most 100 years)."""

    name = "duration"

    def __init__(self, *, min: timedelta = timedelta(0), max: timedelta | None = None) -> None:
        self.min = min
        self.max = max

    def parse(self, text: str) -> timedelta:
        from ..clock import parse_duration

        delta = parse_duration(text)
        if self.max is not None and delta > self.max:
            raise ValueError(f"{text!r} is longer than {_days(self.max)}")
        if delta < self.min:
            raise ValueError(f"{text!r} is shorter than {self.min}")
        return delta


class Seconds(click.ParamType[float]):
    """A timeout: a finite number of seconds in (0, ``max``]."""

    name = "seconds"

    def __init__(self, max: float = 3600.0) -> None:
        self.max = max

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> float:
        try:
            seconds = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number of seconds", param, ctx)
        if not math.isfinite(seconds) or not 0 < seconds <= self.max:
            self.fail(f"{value!r} is not a number of seconds in (0, {self.max:g}]", param, ctx)
        return seconds


def _days(delta: timedelta) -> str:
    years, days = divmod(delta.days, 365)
    return f"{years} years" if years >= 1 and days < 30 else f"{delta.days} days"


UTC_TIME = UtcTime()
EPOCH_TIME = EpochTime()
TIMEOUT = Seconds()


def source_date_epoch_option(func: Any) -> Any:
    """``--source-date-epoch`` [env: SOURCE_DATE_EPOCH] of the verbs that date what they write."""
    return click.option(
        "--source-date-epoch",
        "source_date",
        type=EPOCH_TIME,
        envvar="SOURCE_DATE_EPOCH",
        metavar="SECONDS",
        help="Date outputs with this time, in seconds since 1970, for reproducible builds [env: SOURCE_DATE_EPOCH].",
    )(func)


def sbom_referrers_option(subject: str, made_by: str) -> Callable[[Any], Any]:
    """``--sbom FILE`` (repeatable) of ``ota push`` and ``bundle push``: SBOMs of the pushed
    ``subject`` attached to it as OCI referrers."""
    return click.option(
        "--sbom",
        "sboms",
        multiple=True,
        type=click.Path(dir_okay=False),
        help=f"A CycloneDX or SPDX 3 JSON SBOM of this {subject} ({made_by}) to attach as a referrer. Repeatable.",
    )


def provenance_key_options(*, besides_key: bool) -> Callable[[Any], Any]:
    """``--provenance-key`` (repeatable) and ``--threshold``: who may sign a provenance and how
    many distinct signers are needed, the same in every verb that verifies one (ota verify,
    ota pull, verify X.hcdfz, bundle pull). ``besides_key``: the verb has a ``--key`` (a
    release key) that counts as a signer too (ota verify, ota pull); a bundle has no release
    key, so there every signer is a ``--provenance-key``. The help says which; the meaning is
    otherwise one. Check the values with :func:`load_provenance_keys`."""
    signer = (
        "Another public key (PEM) that may sign the provenance, besides --key (repeatable)."
        if besides_key
        else "A public key (PEM) that may sign the provenance (repeatable)."
    )
    among = "--key and --provenance-key" if besides_key else "--provenance-key"

    def apply(func: Any) -> Any:
        func = click.option(
            "--threshold",
            type=click.IntRange(1, 64),
            default=1,
            show_default=True,
            help=f"Provenance signatures needed, by distinct keys among {among}.",
        )(func)
        return click.option(
            "--provenance-key", "provenance_keys", multiple=True, type=click.Path(dir_okay=False), help=signer
        )(func)

    return apply


def load_provenance_keys(files: tuple[str, ...], threshold: int, *, key: Any = None) -> list[Any]:
    """The public keys that may sign a provenance: ``key`` (a release key already loaded, if
    the verb has one) first, then each ``--provenance-key`` file.

    Raises:
        click.UsageError: ``threshold`` is more than the distinct keys given (exit 2).
        InputError / KeyFileError: a key file that cannot be read (exit 3).
    """
    from ..ota.keys import load_public
    from ..ota.signer import key_id

    keys = ([key] if key is not None else []) + [load_public(f) for f in files]
    if len({key_id(k) for k in keys}) < threshold:
        among = "--key, --provenance-key" if key is not None else "--provenance-key"
        raise click.UsageError(f"--threshold {threshold} needs as many distinct keys ({among})")
    return keys


# --- the per-project config file (hcdf_trust.config), applied the same way to every verb -------
_CONFIG_META = "hcdf_trust.config"  # ctx.meta: the ProjectConfig this run uses (None: none)
_CONFIG_FILE_META = "hcdf_trust.config_file"  # --project-config FILE, or False for --no-project-config
_FROM_CONFIG_META = "hcdf_trust.from_config"  # names of the options the config set


class ConfigOption(click.Option):
    """An option that ``hcdf-trust.toml`` may set (under ``config_key``: ``base``,
    ``registry.site``, ...). A flag (or its environment variable) given on the command line
    overrides the file; the file's value goes through the option's own type and checks."""

    def __init__(self, *args: Any, config_key: str, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.config_key = config_key


def _set_config_file(ctx: click.Context, param: click.Parameter, value: Any) -> None:
    if not value:
        return
    if param.name == "no_project_config":
        ctx.meta[_CONFIG_FILE_META] = False
    elif ctx.meta.get(_CONFIG_FILE_META) is not False:  # --no-project-config wins
        ctx.meta[_CONFIG_FILE_META] = value


CONFIG_OPTIONS = (
    click.Option(
        ["--project-config", "project_config_file"],
        type=click.Path(dir_okay=False),
        expose_value=False,
        is_eager=True,
        callback=_set_config_file,
        help="Read this hcdf-trust.toml instead of looking for one beside DOC and in its parent folders.",
    ),
    click.Option(
        ["--no-project-config"],
        is_flag=True,
        expose_value=False,
        is_eager=True,
        callback=_set_config_file,
        help="Read no hcdf-trust.toml [env: HCDF_TRUST_NO_CONFIG=1].",
    ),
)


def with_project_config(command: click.Command) -> None:
    """Give ``command`` ``--project-config``/``--no-project-config`` and let the project's
    ``hcdf-trust.toml`` default its :class:`ConfigOption` options before it runs. Called once per
    verb, where every verb is looked up (:func:`hcdf_trust.cli._with_shared_options`), so no verb
    can miss it."""
    if getattr(command, "_project_config", False) or command.callback is None:
        return
    command.params.extend(CONFIG_OPTIONS)
    callback = command.callback

    def run(*args: Any, **kwargs: Any) -> Any:
        from ..errors import HcdfTrustError

        try:
            apply_project_config(click.get_current_context(), command, kwargs)
        except HcdfTrustError as exc:  # reported as every verb reports its errors (exit 3, --json)
            from . import fail

            fail([exc], as_json=bool(kwargs.get("as_json")))
        return callback(*args, **kwargs)

    command.callback = run
    command._project_config = True  # type: ignore[attr-defined]


def apply_project_config(ctx: click.Context, command: click.Command, kwargs: dict[str, Any]) -> None:
    """Find (beside DOC, else from the working folder) and read the project's config, record it
    for ``--json`` and the warnings, and put its values into ``kwargs`` for every
    :class:`ConfigOption` not given on the command line.

    Raises:
        ConfigError (exit 3): the file is unsafe, not TOML, has an unknown key, or a value its
            option refuses (named with the file and the key).
    """
    import os

    from .. import config

    chosen = ctx.meta.get(_CONFIG_FILE_META)
    ctx.meta[_CONFIG_META] = None
    if chosen is False or (chosen is None and os.environ.get(config.NO_CONFIG_ENV)):
        return
    if chosen is None:
        doc = kwargs.get("doc")
        start = (os.path.dirname(doc) or ".") if isinstance(doc, str) else "."
        chosen = config.find(start)
        if chosen is None:
            return
    project = config.load(chosen)
    ctx.meta[_CONFIG_META] = project
    ctx.meta[_FROM_CONFIG_META] = taken = set()
    source = click.core.ParameterSource
    for param in command.params:
        if not isinstance(param, ConfigOption) or param.name not in kwargs:
            continue
        key = param.config_key
        if key not in project.values or ctx.get_parameter_source(param.name) not in (source.DEFAULT, None):
            continue
        try:
            kwargs[param.name] = param.process_value(ctx, project.values[key])
            taken.add(param.name)
        except click.BadParameter as exc:
            raise config.ConfigError(
                f"{key}: {exc.message}", file=project.shown, expected=f"a value {param.opts[-1]} accepts"
            ) from None


def project_config() -> Any:
    """The :class:`~hcdf_trust.config.ProjectConfig` of this run, or ``None`` (ctx.meta is
    shared by a verb and its groups)."""
    ctx = click.get_current_context(silent=True)
    return None if ctx is None else ctx.meta.get(_CONFIG_META)


def from_config(name: str) -> bool:
    """Whether the current verb's option ``name`` took its value from the project's config."""
    ctx = click.get_current_context(silent=True)
    return ctx is not None and name in ctx.meta.get(_FROM_CONFIG_META, ())


def acknowledged(code: str) -> bool:
    """Whether the project's config acknowledges warnings with this code."""
    project = project_config()
    return project is not None and code in project.acknowledge
