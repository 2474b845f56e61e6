"""Entry point. Expected failures (PropError) are caught here, once, and printed as one line."""

from __future__ import annotations

import os
import re
import signal
import sys
import warnings

import typer
import typer.core

from prop_cli.constants import DISTRIBUTION, ENV_DEBUG

from . import (
    attack_cmd,
    eval_cmd,
    export_cmd,
    formats_cmd,
    inspect_cmd,
    keygen_cmd,
    personalize_cmd,
    push_cmd,
    run_cmd,
    serve_cmd,
    serve_ray_cmd,
    users_cmd,
    verify_cmd,
)

app = typer.Typer(
    name="prop",
    help="Add private keys to existing neural-network checkpoints (PRoP).",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            number = version(DISTRIBUTION)
        except PackageNotFoundError:  # running from a source tree that pip never installed
            number = "unknown (not installed)"
        print(f"{DISTRIBUTION} {number}")
        raise typer.Exit()


@app.callback()
def _options(
    show_version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """Add private keys to existing neural-network checkpoints (PRoP)."""


# A repeatable option's type as typer >= 0.2x prints it ("<list[Path]>"), shown as one value repeated.
_LIST_TYPE = re.compile(r"<list\[(\w+)\]>")


def _argument(param) -> str:
    """An argument as the commands' help texts name it: CHECKPOINT, [PATH], FILES... (typer >= 0.2x
    prints a required one as {checkpoint}, a shape no shell or man page uses)."""
    name = param.metavar or param.name.upper()
    name = name if param.required else f"[{name}]"
    return name + ("..." if param.nargs != 1 else "")


class Command(typer.core.TyperCommand):
    """typer's command with the help every typer since 0.12 prints the same way where it matters:
    arguments by their upper-case names in the usage line and the list, repeatable options as
    ``<path>...``. The rest (types, defaults, wrapping) is typer's."""

    def collect_usage_pieces(self, ctx) -> list[str]:
        pieces = [self.options_metavar] if self.options_metavar else []
        for param in self.get_params(ctx):
            argument = param.param_type_name == "argument"
            pieces += [_argument(param)] if argument else param.get_usage_pieces(ctx)
        return pieces

    def format_options(self, ctx, formatter) -> None:
        rows: dict[str, list[tuple[str, str]]] = {"argument": [], "option": []}
        for param in self.get_params(ctx):
            record = param.get_help_record(ctx)
            if record is None or param.param_type_name not in rows:
                continue
            name, text = record
            if param.param_type_name == "argument":
                name = _argument(param)
            else:
                name = _LIST_TYPE.sub(lambda m: f"<{m[1].lower()}>...", name)
            rows[param.param_type_name].append((name, text))
        for title, kind in (("Arguments", "argument"), ("Options", "option")):
            if rows[kind]:
                with formatter.section(title):
                    formatter.write_dl(rows[kind])


# The commands, in the order `prop --help` lists them: one file each (users_cmd and verify_cmd hold two).
COMMANDS = {
    "keygen": keygen_cmd.keygen,
    "inspect": inspect_cmd.inspect,
    "personalize": personalize_cmd.personalize,
    "run": run_cmd.run,
    "add-user": users_cmd.add_user,
    "remove-user": users_cmd.remove_user,
    "attack": attack_cmd.attack,
    "eval": eval_cmd.eval_,
    "serve": serve_cmd.serve,
    "serve-ray": serve_ray_cmd.serve_ray,
    "export": export_cmd.export,
    "push": push_cmd.push,
    "verify": verify_cmd.verify,
    "enrol": verify_cmd.enrol,
    "formats": formats_cmd.formats,
}
for _name, _command in COMMANDS.items():
    app.command(_name, cls=Command)(_command)

# Exit codes: 0 ok, 1 a check failed (e.g. attack --max-leak), 2 bad input or usage, 130 interrupted.
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


class Interrupted(BaseException):
    """Ctrl-C, raised by our SIGINT handler instead of KeyboardInterrupt, which typer would swallow
    (exit 130, no message). Not an Exception, so no ``except Exception`` turns it into an error."""


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"prop: warning: {message}", file=sys.stderr)


def _on_sigint(signum, frame) -> None:
    # Only the first Ctrl-C interrupts: a second one must not cut short the clean-up it started.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    raise Interrupted()


def _what_was_written() -> str:
    from prop_cli.files import written

    paths = written()
    return f"wrote {', '.join(map(str, paths))}" if paths else "nothing was written"


def _exit_interrupted(when: str = "") -> None:
    """Say what was written, then leave at once: no traceback from exit hooks (torch's among them)."""
    print(f"prop: interrupted{when}; {_what_was_written()}", file=sys.stderr)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(EXIT_INTERRUPTED)


def _on_late_sigint(signum, frame) -> None:
    _exit_interrupted(" while exiting")


def _usage_errors() -> tuple[type, type | tuple]:
    """The parser's usage errors: typer >= 0.24 carries its own copy of click (``typer._click``), older
    typers use click's. (typer exports Exit and Abort, not these.)"""
    try:
        from typer._click import exceptions
    except ImportError:
        from click import exceptions
    return exceptions.UsageError, getattr(exceptions, "NoArgsIsHelpError", ())


def main() -> None:
    warnings.showwarning = _one_line_warning
    debug = bool(os.environ.get(ENV_DEBUG))
    if not debug:
        signal.signal(signal.SIGINT, _on_sigint)
    usage_error, help_error = _usage_errors()
    try:
        code = app(standalone_mode=False, prog_name="prop")
    except Interrupted:
        _exit_interrupted()
    except help_error as e:  # `prop` alone: the help, as before
        e.show()
        sys.exit(EXIT_BAD_INPUT)
    except usage_error as e:  # a missing or unknown option: the one-line format every error has
        where = e.ctx.command_path if e.ctx is not None else "prop"
        print(f"prop: error: {e.format_message().rstrip('.')}; see {where} --help", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)
    except typer.Abort:  # end of input at a prompt (a passphrase): nothing was written
        print(f"prop: interrupted; {_what_was_written()}", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)
    except Exception as e:
        from prop_cli.errors import PropError

        if not isinstance(e, PropError) or debug:
            raise
        print(f"prop: error: {e.line()}", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)
    else:
        sys.exit(code if isinstance(code, int) else 0)  # typer.Exit(n) returns n without standalone mode
    finally:
        if not debug:  # the work is done; a Ctrl-C during interpreter exit gets a line, not a traceback
            signal.signal(signal.SIGINT, _on_late_sigint)


if __name__ == "__main__":
    main()
