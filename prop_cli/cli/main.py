"""Entry point. Expected failures (PropError) are caught here, once, and printed as one line."""

from __future__ import annotations

import os
import sys
import warnings

import typer

from . import (
    attack_cmd,
    eval_cmd,
    export_cmd,
    formats_cmd,
    inspect_cmd,
    keygen,
    personalize_cmd,
    push_cmd,
    run_cmd,
    users_cmd,
)

app = typer.Typer(
    name="prop",
    help="Add private keys to existing neural-network checkpoints (PRoP).",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)
app.command("keygen")(keygen.keygen)
app.command("inspect")(inspect_cmd.inspect)
app.command("personalize")(personalize_cmd.personalize)
app.command("run")(run_cmd.run)
app.command("add-user")(users_cmd.add_user)
app.command("remove-user")(users_cmd.remove_user)
app.command("attack")(attack_cmd.attack)
app.command("eval")(eval_cmd.eval_)
app.command("export")(export_cmd.export)
app.command("push")(push_cmd.push)
app.command("formats")(formats_cmd.formats)

# Exit codes: 0 ok, 1 a check failed (e.g. attack --max-leak), 2 bad input or usage.
EXIT_BAD_INPUT = 2


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"prop: warning: {message}", file=sys.stderr)


def main() -> None:
    warnings.showwarning = _one_line_warning
    try:
        app()
    except Exception as e:
        from prop_cli.errors import PropError

        if not isinstance(e, PropError) or os.environ.get("PROP_DEBUG"):
            raise
        print(f"prop: error: {e.line()}", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)


if __name__ == "__main__":
    main()
