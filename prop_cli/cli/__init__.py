"""The `prop` command line: a thin typer layer over prop_cli.api."""
