"""The ``hcdf-trust`` command: parses, calls the library, renders. No logic here.

Heavy modules (httpx, rich) are imported inside the commands that
need them, so ``--help`` and an offline ``verify`` start fast.
"""

from __future__ import annotations

import errno
import functools
import gc
import json
import os
import sys
from collections.abc import Callable, Iterable
from typing import Any

import click

from .. import __version__
from ..errors import ErrorGroup, HcdfTrustError, counted, json_locations
from .params import (
    TIMEOUT,
    ConfigOption,
    acknowledged,
    from_config,
    load_provenance_keys,
    project_config,
    provenance_key_options,
    with_project_config,
)

_QUIET = "hcdf_trust.quiet"  # ctx.meta key (one per run, shared by a verb and its groups)


def say(*lines: str, err: bool = True, always: bool = False) -> None:
    """Print a message, each argument one line, through the secret filter (:mod:`hcdf_trust.scrub`:
    credentials, query strings, private keys and passphrases hidden, control characters escaped).
    Every human message of every verb goes through here (stderr unless ``err=False``).
    ``--quiet`` drops the stderr ones unless ``always`` (errors, warnings, findings); results a
    verb prints on stdout are never dropped."""
    if err and not always and _is_quiet():
        return
    from ..scrub import scrub

    click.echo("\n".join(scrub(line) for line in lines), err=err)  # noqa: TID251 -- the one place that prints messages


def _is_quiet() -> bool:
    ctx = click.get_current_context(silent=True)
    return ctx is not None and bool(ctx.meta.get(_QUIET))


def _set_quiet(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if value:
        ctx.meta[_QUIET] = True


def _with_shared_options(command: click.Command) -> click.Command:
    """Give ``command`` (and, for a group, each of its verbs) the options every verb has:
    ``-q/--quiet``. Added here, where every verb is looked up, so no verb can miss it."""
    if isinstance(command, click.Group):
        for sub in command.commands.values():
            _with_shared_options(sub)
    elif not any(p.name == "quiet" for p in command.params):
        with_project_config(command)
        command.params.append(
            click.Option(
                ["-q", "--quiet"],
                is_flag=True,
                expose_value=False,
                is_eager=True,
                callback=_set_quiet,
                help="Print only errors and warnings on stderr (results on stdout stay).",
            )
        )
    return command


def emit_json(payload: dict[str, Any]) -> None:
    """The one JSON object of ``--json``, through the secret filter: indented on a terminal,
    compact into a pipe or file (where json's C encoder writes a 10,000-link macsec plan in
    0.1 s instead of 0.4 s). Every object has ``errors`` (docs/commands.md's shape), empty when the
    verb gave none."""
    from ..scrub import scrub_json

    if "errors" not in payload:
        payload = {**payload, "errors": []}
    if "config" not in payload:  # which hcdf-trust.toml set defaults (None: none was read)
        project = project_config()
        payload = {**payload, "config": None if project is None else project.shown}
    indent = 2 if sys.stdout.isatty() else None
    payload = json_locations(payload)  # a JSON document's locations: "pointer", not a line
    click.echo(json.dumps(scrub_json(payload), indent=indent, sort_keys=True))  # noqa: TID251 -- filtered above


def fail(errors: list[HcdfTrustError], *, as_json: bool, payload: dict[str, Any] | None = None) -> None:
    """Report errors (stderr, or JSON on stdout) and exit with the contract's code."""
    group = ErrorGroup(errors)
    if as_json:
        out = dict(payload or {})
        out["ok"] = False
        out["errors"] = [e.to_dict() for e in errors]
        emit_json(out)
    else:
        for e in errors:
            first, *rest = e.lines()
            say(f"error: {first}", *rest, always=True)
    sys.exit(group.exit_code)


def handle_errors(func: Callable[..., Any]) -> Callable[..., Any]:
    """Turn a library exception into the exit code and message of the CLI contract."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except HcdfTrustError as exc:
            errors = exc.errors if isinstance(exc, ErrorGroup) else [exc]
            fail(errors, as_json=bool(kwargs.get("as_json")))

    return wrapper


def _is_url(text: str) -> bool:
    return "://" in text


def _check_url(value: str, ctx: click.Context, *, what: str) -> None:
    """A flag's URL must be https (or http under --allow-http). Credentials are left to
    the library, which refuses them with exit 3; messages show URLs redacted."""
    from urllib.parse import urlsplit

    from ..include.locate import redact

    scheme = value.partition("://")[0].lower()
    if scheme == "https" or (scheme == "http" and ctx.params.get("allow_http")):
        try:
            parts = urlsplit(value)
            parts.port  # noqa: B018 -- raises ValueError for a port that is not a number in 0-65535
        except ValueError as exc:
            raise click.BadParameter(f"{what} {redact(value)!r} is not a valid URL: {exc}") from None
        if not parts.hostname or "\\" in value:
            raise click.BadParameter(f"{what} {redact(value)!r} is not a valid URL: expected {scheme}://host/path")
        return
    hint = " (plain http needs --allow-http)" if scheme == "http" and "allow_http" in ctx.params else ""
    raise click.BadParameter(f"{what} {redact(value)!r} is not an https:// URL{hint}")


def _check_folder(value: str, *, what: str) -> None:
    if not os.path.exists(value):
        raise click.BadParameter(f"{what} {value!r} does not exist")
    if not os.path.isdir(value):
        raise click.BadParameter(f"{what} {value!r} is not a folder")


def _mirror(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    from ..include.locate import redact

    out = []
    for value in values:
        prefix, sep, target = value.partition("=")
        if not sep or not prefix or not target:
            raise click.BadParameter(f"{redact(value)!r} is not PREFIX=DIR|URL")
        if prefix.partition("://")[0].lower() not in ("https", "http", "file"):  # it would never match, silently
            raise click.BadParameter(f"prefix {redact(prefix)!r} is not a URL prefix (https://host/...)")
        if _is_url(target):
            _check_url(target, ctx, what="target")
        else:
            _check_folder(target, what="target")
        out.append((prefix, target))
    return tuple(out)


def _base(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    if value is not None:
        if _is_url(value):
            _check_url(value, ctx, what="URL")
        else:
            _check_folder(value, what="folder")
    return value


# The options that say where a description tree is, shared by every verb that reads one, so
# that each means the same and reads the same in every --help (tests/test_flags_uniform.py).
LOCK_OPTION = click.option(
    "--lock", "lock_path", type=click.Path(dir_okay=False), help="Lock file [default: DOC.lock beside DOC]."
)
CACHE_DIR_OPTION = click.option(
    "--cache-dir",
    cls=ConfigOption,
    config_key="cache-dir",
    type=click.Path(file_okay=False),
    help="Content-addressed cache [default: ~/.cache/hcdf-trust].",
)
BASE_OPTION = click.option(
    "--base",
    cls=ConfigOption,
    config_key="base",
    callback=_base,
    metavar="DIR|URL",
    help="Existing folder, or https URL, that relative references resolve against (default: the referencing document).",
)
ROOT_OPTION = click.option(
    "--root",
    cls=ConfigOption,
    config_key="root",
    type=click.Path(exists=True, file_okay=False),
    help="Folder that local references may not leave [default: --base if a folder, else DOC's folder].",
)
MIRROR_OPTION = click.option(
    "--mirror",
    "mirrors",
    cls=ConfigOption,
    config_key="mirror",
    multiple=True,
    callback=_mirror,
    metavar="PREFIX=DIR|URL",
    help="Rewrite a URL prefix to an existing folder or an https URL (repeatable).",
)
OFFLINE_HELP = "Use only local files, mirrors and the cache; never open a socket."
JSON_OPTION = click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
# Every verb that talks https (a registry, a site, --previous, an online tree) trusts the same
# extra CAs, named the same way; the environment variable is the fallback of the flag.
CA_BUNDLE_OPTION = click.option(
    "--ca-bundle",
    type=click.Path(dir_okay=False, exists=True),
    envvar="HCDF_TRUST_CA_BUNDLE",
    help="PEM file of CA certificates to trust for https, besides the system's (a loopback OCI registry "
    "then speaks https too) [env: HCDF_TRUST_CA_BUNDLE].",
)
INSECURE_REGISTRY_OPTION = click.option(
    "--insecure-registry",
    "insecure_registries",
    multiple=True,
    metavar="HOST[:PORT]",
    help="Talk plain http to this OCI registry (loopback hosts need no flag; never credentials "
    "off this machine). Repeatable.",
)
SCHEMA_ENV = "HCDF_TRUST_SCHEMA"  # jsonform.SCHEMA_ENV, without importing it
SCHEMA_HELP = (
    "HCDF schema (hcdf.xsd) that documents in HCDF's JSON form are read through (repeatable: the one "
    f"whose version fits the document's is used) [env: {SCHEMA_ENV}]."
)


def use_schemas(ctx: click.Context, param: click.Parameter, value: tuple[str, ...] | None) -> tuple[str, ...]:
    """Record the ``--schema`` files for this run's JSON documents (:func:`hcdf_trust.jsonform.use_schemas`)."""
    if value or "hcdf_trust.jsonform" in sys.modules:  # an XML-only run never imports it
        from .. import jsonform

        jsonform.use_schemas(value or ())
    return value or ()


SCHEMA_OPTION = click.option(
    "--schema",
    "schemas",
    multiple=True,
    type=click.Path(dir_okay=False),
    envvar=SCHEMA_ENV,
    callback=use_schemas,
    expose_value=False,
    help=SCHEMA_HELP,
)
_LOCATION_KEYS = ("base", "mirrors", "root")
_TREE_KEYS = (*_LOCATION_KEYS, "cache_dir", "lock_path", "offline", "ca_bundle")


def tree_location_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """``--base``, ``--mirror``, ``--root`` (resolve's), passed to ``func`` as one
    ``tree``: a :class:`~hcdf_trust.include.resolver.TreeOptions`. For a verb that reads
    local files only (validate)."""
    return _tree_decorator(func, (BASE_OPTION, MIRROR_OPTION, ROOT_OPTION), _LOCATION_KEYS)


def tree_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Resolve's ``--base``, ``--mirror``, ``--root``, ``--cache-dir``, ``--lock``,
    ``--offline`` (default here; ``--online`` fetches what the cache lacks, still checked
    against the lock) and ``--ca-bundle``, passed to ``func`` as one ``tree``: a
    :class:`~hcdf_trust.include.resolver.TreeOptions`. For every verb that reads a description
    tree under its lock (audit, sbom, macsec, ota build, bundle, fleet); a verb's own https
    (a registry, --previous) takes ``tree.ca_bundle`` too: one flag, one meaning."""
    offline = click.option(
        "--offline/--online",
        default=True,
        show_default=True,
        help=OFFLINE_HELP + " --online fetches what they lack (still checked against the lock).",
    )
    options = (
        LOCK_OPTION,
        CACHE_DIR_OPTION,
        BASE_OPTION,
        ROOT_OPTION,
        MIRROR_OPTION,
        offline,
        CA_BUNDLE_OPTION,
        SCHEMA_OPTION,
    )
    return _tree_decorator(func, options, _TREE_KEYS)


def _tree_decorator(func: Callable[..., Any], options: tuple[Any, ...], keys: tuple[str, ...]) -> Callable[..., Any]:
    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        from ..include.resolver import TreeOptions

        return func(*args, tree=TreeOptions(**{k: kwargs.pop(k) for k in keys}), **kwargs)

    for option in reversed(options):
        wrapper = option(wrapper)
    return wrapper


def resolve_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Options of every verb that resolves a document tree (resolve, verify, pin); none is about the network."""
    options = [
        LOCK_OPTION,
        CACHE_DIR_OPTION,
        BASE_OPTION,
        ROOT_OPTION,
        MIRROR_OPTION,
        click.option(
            "--max-depth",
            type=click.IntRange(1, 1_000_000),
            default=16,
            show_default=True,
            help="Deepest include nesting accepted.",
        ),
        click.option(
            "--strict",
            is_flag=True,
            help="Refuse weak pins (hex prefixes shorter than 64 digits).",
        ),
        JSON_OPTION,
        SCHEMA_OPTION,
    ]
    for option in reversed(options):
        func = option(func)
    return func


def _registry_options(*, urls: bool) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--registry`` and ``--trusted-root`` (checks: hcdf_trust.registry.resolution); ``urls``: the
    verb may fetch, so the site may be an http(s) URL (resolve), else only a folder (verify)."""
    site = (
        "an http(s) URL (not with --offline) or a folder holding a copy of the published site"
        if urls
        else "a folder holding a copy of the published site (verify never fetches)"
    )

    def decorate(func: Callable[..., Any]) -> Callable[..., Any]:
        func = click.option(
            "--trusted-root",
            cls=ConfigOption,
            config_key="registry.trusted-root",
            type=click.Path(dir_okay=False),
            help="The registry's root.json you trust (with --registry).",
        )(func)
        return click.option(
            "--registry",
            "registry_site",
            cls=ConfigOption,
            config_key="registry.site",
            metavar="URL|DIR" if urls else "DIR",
            help=f"Check extensions and stream profiles against this signed registry: {site}. Needs "
            "--trusted-root; with --strict, unregistered extension domains and versions are errors too.",
        )(func)

    return decorate


registry_options = _registry_options(urls=True)
offline_registry_options = _registry_options(urls=False)


def _registry(
    site: str | None,
    trusted_root: str | None,
    *,
    strict: bool,
    offline: bool,
    persist: bool,
    timeout: float,
    ca_bundle: str | None = None,
) -> Any:
    if site is None:
        if trusted_root is not None:
            raise click.UsageError("--trusted-root goes with --registry")
        return None
    if trusted_root is None:
        raise click.UsageError("--registry needs --trusted-root")
    if offline and _is_url(site):
        if from_config("registry_site"):  # a project's URL registry: checked by the verbs that fetch
            say(f"note: registry.site of {project_config().shown} is a URL; this offline run does not check it")
            return None
        raise click.UsageError(f"--registry {site!r} is a URL, and this run is offline: give a folder copy of the site")
    from ..registry.resolution import RegistryCheck

    return RegistryCheck.open(site, trusted_root, strict=strict, persist=persist, ca_bundle=ca_bundle, timeout=timeout)


def fetch_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Options of the verbs that may fetch (resolve, pin); verify never does, and neither offers nor reads them."""
    options = [
        click.option("--offline", is_flag=True, help=OFFLINE_HELP),
        click.option(
            "--allow-http",
            is_flag=True,
            is_eager=True,  # read by the --base and --mirror checks, whatever the order on the command line
            help="Allow plain http:// for references pinned with a full SHA-256.",
        ),
        click.option(
            "--jobs",
            "-j",
            type=click.IntRange(1, 64),
            default=16,
            show_default=True,
            help="Parallel network fetches (local hashing uses one thread per core).",
        ),
        CA_BUNDLE_OPTION,
        click.option(
            "--timeout",
            type=TIMEOUT,
            default=30.0,
            show_default=True,
            help="Seconds without data before a fetch fails.",
        ),
        click.option(
            "--max-size",
            "max_bytes",
            type=click.IntRange(1, 1 << 40),
            default=4 << 30,
            show_default=True,
            help="Largest body accepted from a server, in bytes.",
        ),
    ]
    for option in reversed(options):
        func = option(func)
    return func


class _ClosedStdout:
    """Standard output when the process was started with it closed (``>&-``): every write fails,
    so a verb that prints its result exits 3 instead of printing nothing and succeeding."""

    def write(self, data: object) -> int:
        raise OSError(errno.EBADF, "standard output is closed")

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False

    @property
    def buffer(self) -> _ClosedStdout:  # sys.stdout.buffer.write(bytes) fails the same way
        return self


def _standard_streams() -> None:
    """Keep descriptors 0-2 taken (/dev/null where the process was started with one closed), so
    that no file this run opens becomes its stdout or stderr; a closed stdout then refuses writes."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            null = os.open(os.devnull, os.O_RDWR)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
    if sys.stdout is None:  # Python found fd 1 closed at start (it may hold another file by now)
        sys.stdout = _ClosedStdout()


def _stdout_failed(exc: OSError) -> None:
    """When standard output cannot be written (closed, full, a closed pipe), say so and exit 3;
    otherwise return (``exc`` is someone else's to report)."""
    stream: Any = sys.stdout
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    frame = tb.tb_frame if tb is not None else None
    # every line a verb prints goes through click.echo (in say and emit_json; err=False: stdout), which flushes it
    echoed = frame is not None and frame.f_code.co_name == "echo" and frame.f_globals.get("__name__") == "click.utils"
    if not (isinstance(stream, _ClosedStdout) or (echoed and frame is not None and not frame.f_locals.get("err"))):
        return
    try:  # what is still buffered goes nowhere, so the exit's own flush does not fail again
        fd = stream.fileno()
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, fd)
        os.close(null)
    except (AttributeError, OSError, ValueError):
        pass
    why = exc.strerror or str(exc)
    say(f"error: cannot write to standard output: {why}", always=True)
    raise click.exceptions.Exit(3)


# Objects that a console-script run leaves for the kernel to reclaim (see _Main); None in-process.
_KEPT: list[object] | None = None


def keep_until_exit(obj: object) -> None:
    """Leave ``obj`` alive to the end of a console-script run, so that it is never freed
    object by object (a 10,000-file Resolution and its XML trees: ~30 ms). In-process
    callers (tests, CliRunner) are unaffected."""
    if _KEPT is not None:
        _KEPT.append(obj)


class _Main(click.Group):
    """The ``hcdf-trust`` group. As the console script (``main()``, arguments from
    ``sys.argv``), it ends the process with ``os._exit`` once the command is done, its
    output flushed and its atexit handlers run: tearing the interpreter down frees every
    module and object one by one (~20 ms, more after a large tree) and changes nothing
    a user can see. With another thread still alive, or output that cannot be flushed,
    the process exits as usual; ``main(args)`` and ``main.main()`` always return or raise.
    An interrupt exits 130, as shells report SIGINT, not click's 1 ("Aborted!"), which a
    build script would read as an integrity failure."""

    def main(self, *args: Any, **kwargs: Any) -> Any:
        from ..scrub import forget_all

        forget_all()  # an in-process caller's previous run: its passphrases are not this run's
        _standard_streams()
        return super().main(*args, **kwargs)

    def make_context(self, *args: Any, **kwargs: Any) -> click.Context:
        try:
            return super().make_context(*args, **kwargs)
        except click.ClickException as exc:
            raise _scrubbed(exc) from None
        except OSError as exc:  # --help into a full or closed stdout
            _stdout_failed(exc)
            raise

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            say("interrupted: nothing more was written", always=True)
            ctx.exit(130)
        except click.ClickException as exc:  # a usage error of a verb: click prints it, filtered
            raise _scrubbed(exc) from None
        except OSError as exc:
            _stdout_failed(exc)
            raise

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*super().list_commands(ctx), *_LAZY_COMMANDS})

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name in _LAZY_COMMANDS and cmd_name not in self.commands:
            import importlib

            module, attr = _LAZY_COMMANDS[cmd_name]
            self.add_command(getattr(importlib.import_module(module, __name__), attr), cmd_name)
        command = super().get_command(ctx, cmd_name)
        return None if command is None else _with_shared_options(command)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        global _KEPT
        if args or kwargs:
            return self.main(*args, **kwargs)
        _KEPT = []
        try:
            return self.main(*args, **kwargs)
        except SystemExit as exc:
            _leave(exc.code)
            raise


def _scrubbed(exc: click.ClickException) -> click.ClickException:
    """Click's own error (a bad value, an unknown option) with its message through the secret
    filter: a key given to the wrong option is not echoed back."""
    from ..scrub import scrub

    exc.message = scrub(exc.message)  # type: ignore[misc]  # Final in click's stubs; rewritten once, here
    return exc


def _leave(code: object) -> None:
    """``os._exit`` with ``sys.exit(code)``'s status, when nothing else is left to do."""
    import atexit
    import threading

    if threading.active_count() > 1:
        return
    if code is None:
        status = 0
    elif isinstance(code, int):
        status = code
    else:
        return  # a message to print: the usual exit prints it
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
    except BaseException:  # noqa: BLE001 -- the usual exit reports it
        return
    os._exit(status)


@click.group(cls=_Main, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="hcdf-trust")
@click.pass_context
def main(ctx: click.Context) -> None:
    """Verify, lock and flatten everything an HCDF robot description references.

    Exit codes: 0 success, 1 integrity failure (digest mismatch, lock drift, bad
    signature), 2 usage error, 3 input error (missing or malformed file, network),
    130 interrupted (Ctrl-C).
    """
    # A run builds a few objects per reference and keeps them to its end: the cyclic
    # collector would rescan them over and over and free nothing (60 ms of a 10,000-file
    # resolve). Off for the one command; reference counting still frees as it goes.
    # In-process callers get it back; a console-script run ends with it off (turned on,
    # its first collection would scan every object of the run once more). Not for the
    # verbs that drive python-tuf, imgtool and cwt: their object graphs are not ours to vouch for.
    if gc.isenabled() and ctx.invoked_subcommand not in ("ota", "registry"):
        gc.disable()
        if _KEPT is None:
            ctx.call_on_close(gc.enable)


_VALUE_LEFT_OUT = "hcdf_trust.value_left_out"  # ctx.meta: (option, the word read as the positional)


class _OptionalValueCommand(click.Command):
    """A command with one positional argument and an option whose value may be omitted
    (resolve's ``--update [URI]``). Click gives such an option the next word as its value,
    so ``resolve --update robot.hcdf`` lost DOC ("Missing argument"); when that leaves no
    positional argument at all, the word was the positional: the option gets no value."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        options = [p for p in self.params if isinstance(p, click.Option)]
        optional = {o for p in options if p._flag_needs_value for o in p.opts}
        valued = {o for p in options if not p.is_flag and not p.count and not p._flag_needs_value for o in p.opts}
        args = list(args)
        positionals, omitted, i = 0, None, 0
        while i < len(args):
            word = args[i]
            if word == "--":
                positionals += len(args) - i - 1
                break
            if word.startswith("-") and len(word) > 1:
                follows = i + 1 < len(args) and not args[i + 1].startswith("-")
                if word in valued:
                    i += 2
                    continue
                if word in optional and follows:
                    omitted, i = i, i + 2
                    continue
            else:
                positionals += 1
            i += 1
        if positionals == 0 and omitted is not None:
            args[omitted] += "="  # "--update=": the value left out; the next word is the positional
            ctx.meta[_VALUE_LEFT_OUT] = (args[omitted][:-1], args[omitted + 1])
        return super().parse_args(ctx, args)


@main.command(cls=_OptionalValueCommand)
@click.argument("doc", type=click.Path(dir_okay=False))
@resolve_options
@click.option(
    "--locked", is_flag=True, help="Fail (exit 1) if anything differs from the lock file or is missing from it."
)
@fetch_options
@click.option(
    "-o",
    "--out",
    "out",
    type=click.Path(dir_okay=False),
    help="Write one flattened document with every include expanded.",
)
@click.option(
    "--max-elements",
    # At most xml.MAX_DOCUMENT_ELEMENTS (not imported: lxml stays out of start-up), so that
    # what is written can be read again; tests/test_bounds.py checks the two agree.
    type=click.IntRange(1, 1_000_000),
    default=250_000,
    show_default=True,
    help="Most elements the --out document may have once every include is expanded.",
)
@click.option("--no-lock", is_flag=True, help="Do not write the lock file.")
@registry_options
@click.option(
    "--update",
    "update",
    multiple=True,
    is_flag=False,
    flag_value="",
    metavar="[URI]",
    help="Accept new content for a reference the lock pins: --update alone re-pins every entry, "
    "--update URI (repeatable; the uri as written, the lock's url, the file's URL or its path) only that one.",
)
@handle_errors
def resolve(
    doc: str,
    out: str | None,
    max_elements: int,
    no_lock: bool,
    update: tuple[str, ...],
    as_json: bool,
    registry_site: str | None,
    trusted_root: str | None,
    **kw: Any,
) -> None:
    """Fetch every file DOC references, verify its SHA-256, cache it, write the lock file.

    Relative references resolve against the referencing document, or against
    --base. Nothing is written unless every reference verifies, and a lock file
    (or --out) that would not change is left untouched. The lock is the
    pin of every reference without a full sha (trust on first use): content that
    changed since it was locked fails (exit 1) until accepted with --update.
    With --locked the lock is checked, never written. With --registry, the tree's
    extensions and stream profiles are also checked against a signed registry.
    """
    from ..include.locate import display_path
    from ..include.resolver import ResolveOptions
    from ..outputs import OutputPlan, protect_inputs

    if update and kw["locked"]:
        raise click.UsageError("--update and --locked contradict each other: --locked never changes the lock")
    options = ResolveOptions(update_all="" in update, update=tuple(u for u in update if u), **kw)
    from ..bundle import is_bundle

    if out and is_bundle(out):  # every verb would read it as a ZIP: bundles are written by `bundle`
        raise click.UsageError(
            f"--out {out}: a flattened document is XML, not a bundle (hcdf-trust bundle writes those)"
        )
    if is_bundle(doc):  # its pins are in it: it has no lock to write, and it is already flat
        if out or update:
            raise click.UsageError(f"{'--out' if out else '--update'} does not apply to a bundle ({doc})")
        no_lock = True
    no_lock = no_lock or options.locked
    registry = _registry(
        registry_site,
        trusted_root,
        strict=options.strict,
        offline=options.offline,
        persist=True,
        ca_bundle=options.ca_bundle,
        timeout=options.timeout,  # --timeout: the registry's fetches too
    )
    res = _run_resolve(doc, options, as_json=as_json, registry=registry)
    # Every output is checked against every input before any is written; all land or none.
    plan = OutputPlan()
    protect_inputs(plan, res, doc=doc, options=options)
    if registry is not None:
        registry.protect(plan)
    # An output that already holds exactly these bytes is left alone (if_changed): a
    # rebuild over an unchanged tree touches no file, so a build system sees nothing new.
    if no_lock:
        if res.bundle is None:
            plan.protect(res.lock_path, what="the lock file")
    else:
        lock = res.render_lock()
        if options.lock_path is None:
            _lock_beside_doc_writable(res.lock_path, lock)
        plan.add(res.lock_path, lock, flag="--lock", if_changed=True)
    if out:
        from ..include.flatten import flatten
        from ..outputs import DOCUMENT, ORDINARY

        flat = (ORDINARY, DOCUMENT)  # the previous flattened document; never one of the tree (an input)
        plan.check(out, flag="--out", replaces=flat)  # an input is named as such, before flattening
        plan.add(
            out,
            flatten(res, out_path=out, root=options.root, base=options.base, max_elements=max_elements),
            flag="--out",
            if_changed=True,
            replaces=flat,
        )
    wrote = plan.commit()
    if update:
        _say_updates(res, update_all="" in update)
    _report(
        res,
        as_json=as_json,
        wrote=[display_path(p) for p in wrote],
        unchanged=[display_path(p) for p in plan.unchanged],
    )


@main.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@resolve_options
@offline_registry_options
@click.option(
    "--provenance",
    is_flag=True,
    help="Also verify DOC.intoto.json, a bundle's provenance (signed by --provenance-key).",
)
@provenance_key_options(besides_key=False)
@handle_errors
def verify(
    doc: str,
    as_json: bool,
    registry_site: str | None,
    trusted_root: str | None,
    provenance: bool,
    provenance_keys: tuple[str, ...],
    threshold: int,
    **kw: Any,
) -> None:
    """Check DOC's tree against its lock file, offline; write nothing.

    Every file must be present locally, in a mirror or in the cache, and match
    both its pin and the lock. --registry (a folder) also checks the tree's
    extensions and stream profiles against a signed registry. For a bundle,
    --provenance also checks DOC.intoto.json (`bundle --provenance`): its
    signatures, that its subject is this bundle and its dependencies its assets.
    """
    from ..include.resolver import ResolveOptions

    if not provenance and (provenance_keys or threshold != 1):
        raise click.UsageError("--provenance-key and --threshold need --provenance")
    if provenance:
        from ..bundle import is_bundle

        if not is_bundle(doc):
            raise click.UsageError("--provenance verifies a bundle's (DOC.hcdfz); a release's is `ota verify`'s")
        if not provenance_keys:
            raise click.UsageError("--provenance needs --provenance-key (the public key that signed it)")
    options = ResolveOptions(**kw)
    registry = _registry(
        registry_site, trusted_root, strict=options.strict, offline=True, persist=False, timeout=options.timeout
    )
    res = _run_resolve(doc, options, as_json=as_json, registry=registry, verifying=True)
    if provenance:
        errors = _verify_bundle_provenance(doc, provenance_keys, threshold)
        if errors:
            fail(errors, as_json=as_json, payload=_payload(res))
    _report(res, as_json=as_json, wrote=[])


def _verify_bundle_provenance(doc: str, key_files: tuple[str, ...], threshold: int) -> list[Any]:
    """The violations of ``doc``'s provenance (``doc.intoto.json``), keys read from ``key_files``."""
    from ..bundle import read_archive
    from ..errors import display_path
    from ..localfile import read_input
    from ..provenance import dsse
    from ..provenance.bundle import envelope_path, verify_bundle_provenance

    keys = load_provenance_keys(key_files, threshold)
    path = envelope_path(doc)
    data = read_input(path, limit=dsse.MAX_ENVELOPE_BYTES, what="provenance")
    archive = read_archive(doc)
    try:
        return verify_bundle_provenance(archive, data, keys, threshold=threshold, source=display_path(path))
    finally:
        archive.close()


def _lock_beside_doc_writable(lock_path: Any, data: bytes) -> None:
    """The default lock goes beside DOC. In a folder this user cannot write (a read-only checkout
    of someone else's content, a read-only mount) a lock that would change is a usage error
    naming --lock, before anything is written: never a half-done run, never a write into that
    tree by a user who can override its mode. A lock that is already up to date is fine."""
    folder = os.path.dirname(lock_path) or "."
    if os.access(folder, os.W_OK):
        return
    from ..errors import display_path
    from ..localfile import read_input

    try:
        if read_input(lock_path, limit=len(data), what="lock file") == data:
            return
    except HcdfTrustError:
        pass  # none, or another one (over the limit, unreadable): it would be written

    name = os.path.basename(lock_path)
    raise click.UsageError(
        f"DOC's folder {display_path(folder)} is not writable (a read-only checkout?), so the lock file cannot "
        f"be written beside it as {display_path(lock_path)}: name one you can write with --lock "
        f"(e.g. --lock {name}), or pass --no-lock"
    )


def _say_updates(res: Any, *, update_all: bool) -> None:
    """What ``--update`` did: each lock entry it changed, or that it changed none; and, when
    ``--update DOC`` was read as ``--update`` alone, that this re-opened every entry."""
    left_out = click.get_current_context().meta.get(_VALUE_LEFT_OUT)
    if left_out is not None:
        option, word = left_out
        say(f"note: {option} took no URI ({word} is DOC), so every entry of the lock could take new content")
    before = res.locked.entries if res.locked is not None else {}
    changed = [(before[e.url], e) for e in res.lock_entries() if e.url in before and before[e.url].sha256 != e.sha256]
    for old, new in changed:
        say(f"updated {new.uri}: sha256 {old.sha256} -> {new.sha256}")
    if not changed:
        which = "the lock" if update_all else "the named entries"
        say(f"--update: nothing to accept, {which} already matched the content")


def _run_resolve(doc: str, options: Any, *, as_json: bool, registry: Any = None, verifying: bool = False) -> Any:
    """The library's resolve (or, ``verifying``, its verify: locked, offline, no cache writes),
    with a progress bar, then the registry checks; exits on any error."""
    from ..include.resolver import resolve, verify

    run = verify if verifying else resolve
    with _progress(enabled=not as_json) as (on_start, on_progress):
        res = run(doc, options, on_start=on_start, on_progress=on_progress)
    if res.ok and registry is not None:  # a step after resolution: the tree verified, now its registry checks
        errors, warnings = registry.check(res, cache_dir=options.cache_dir)
        res.errors += errors
        res.warnings += warnings
    if not res.ok:
        if not as_json:
            warn(res.warnings)
        fail(res.errors, as_json=as_json, payload=_payload(res))
    keep_until_exit(res)
    return res


class _progress:
    """A rich progress bar on stderr when it is a terminal; otherwise nothing."""

    def __init__(self, *, enabled: bool) -> None:
        self.enabled = enabled and sys.stderr.isatty() and not _is_quiet()
        self.bar: Any = None

    def __enter__(self) -> tuple[Callable[[int], None] | None, Callable[[int, int], None] | None]:
        if not self.enabled:
            return None, None
        from rich.console import Console
        from rich.filesize import decimal
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self.bar = Progress(
            TextColumn("resolving"),
            BarColumn(),
            TextColumn("{task.completed}/{task.total} files"),
            TextColumn("{task.fields[verified]} hashed"),
            TimeElapsedColumn(),
            console=Console(stderr=True),
            transient=True,
        )
        self.bar.start()
        self.task = self.bar.add_task("resolve", total=0, verified=decimal(0))
        self.bytes = 0

        def on_start(n: int) -> None:
            self.bar.update(self.task, total=(self.bar.tasks[0].total or 0) + n)

        def on_progress(files: int, nbytes: int) -> None:
            self.bytes += nbytes
            self.bar.update(self.task, advance=files, verified=decimal(self.bytes))

        return on_start, on_progress

    def __exit__(self, *exc: Any) -> None:
        if self.bar is not None:
            self.bar.stop()


def _payload(res: Any) -> dict[str, Any]:
    from ..document import Kind
    from ..include.resolver import display_url

    artifacts = []
    for art in sorted(res.artifacts.values(), key=lambda a: a.url):
        artifacts.append(
            {
                "kind": art.kind.value,
                "uri": art.uri,
                "url": res.lock_url(art.url),
                "sha256": art.sha256,
                "size": art.size,
                "pin": art.pin_status,
                "source": art.source,
                "referenced_from": sorted({f"{u.doc}:{u.ref.line}" for u in art.uses}),
            }
        )
    firmware = [
        {"name": r.name, "version": r.version, "hash": r.sha, "file": src, "line": r.line}
        for src, r in res.others
        if r.kind is Kind.FIRMWARE
    ]
    extensions = [
        {"domain": r.domain, "version": r.version, "file": src, "line": r.line}
        for src, r in res.others
        if r.kind is Kind.EXTENSION
    ]
    return {
        "ok": res.ok,
        "root": display_url(res.root_location.url),
        "artifacts": artifacts,
        "firmware": firmware,
        "extensions": extensions,
        "summary": _summary(res),
        "warnings": [w.to_dict() for w in res.warnings],
        "errors": [e.to_dict() for e in res.errors],
    }


def warn(notices: Iterable[Any]) -> None:
    """Say each warning once: one line per fact, not per reference (the same code about the
    same file, from several places, is one line naming the other places); not at all when the
    project's ``hcdf-trust.toml`` acknowledges its code, or when it is ``repeated`` (an earlier
    run said it when it wrote the lock that now covers it). ``--json`` lists every one."""
    said: dict[tuple[str, str], list[Any]] = {}
    for n in notices:
        if n.repeated or acknowledged(n.code):
            continue
        key = (n.code, n.url) if n.url is not None else (n.code, str(n))
        said.setdefault(key, []).append(n)
    for first, *more in said.values():
        others = list(dict.fromkeys(p for p in map(_place, more) if p != _place(first)))
        also = ""
        if others:
            also = f" (also at {', '.join(others[:3])}{', ...' if len(others) > 3 else ''})"
        say(f"warning: {first}{also}", always=True)


def _place(n: Any) -> str:
    from ..errors import display_place

    file = display_place(n.file) if n.file else "?"
    return f"{file}:{n.line}" if n.line else file


def _summary(res: Any) -> dict[str, int]:
    arts = list(res.artifacts.values())
    status = [a.pin_status for a in arts]
    return {
        "references": sum(len(a.uses) for a in arts),
        "files": len(arts),
        "pinned": status.count("full"),
        "weak": status.count("weak"),
        "unpinned": status.count("unpinned"),
        "bytes_verified": sum(a.size or 0 for a in arts),
        "from_cache": sum(1 for a in arts if a.source == "cache"),
        "fetched": sum(1 for a in arts if a.source == "network"),
        "local": sum(1 for a in arts if a.source in ("file", "mirror")),
    }


def _report(res: Any, *, as_json: bool, wrote: list[str], unchanged: list[str] | None = None) -> None:
    """The run's summary; ``unchanged``: outputs already in place, not rewritten (resolve only)."""
    if as_json:
        payload = _payload(res)
        payload["wrote"] = wrote
        if unchanged is not None:
            payload["unchanged"] = unchanged
        emit_json(payload)
        return
    warn(res.warnings)
    s = _summary(res)
    say(
        f"{counted(s['references'], 'reference')} to {counted(s['files'], 'file')}: "
        f"{s['pinned']} pinned, {s['weak']} weak, "
        f"{s['unpinned']} unpinned; {s['bytes_verified']} bytes verified "
        f"({s['local']} local, {s['from_cache']} from cache, {s['fetched']} fetched)"
    )
    for path in wrote:
        say(f"wrote {path}")
    for path in unchanged or ():
        say(f"unchanged {path}")


# The verb groups and the verbs other than resolve and verify, each imported when it
# runs or --help lists it (a resolve needs none of them: ~7 ms of start-up, ~1 ms of
# it building pin's and validate's options). Name -> (module, attribute).
_LAZY_COMMANDS = {
    "audit": (".audit", "audit_cmd"),
    "bundle": (".bundle", "bundle"),
    "convert": (".convert", "convert"),
    "fleet": (".fleet", "fleet"),
    "macsec": (".macsec", "macsec"),
    "ota": (".ota", "ota"),
    "pin": (".pin", "pin"),
    "registry": (".registry", "registry"),
    "sbom": (".sbom", "sbom"),
    "validate": (".validate", "validate"),
}
