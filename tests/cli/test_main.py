"""The app as a whole (prop_cli/cli/main.py): help, version, usage errors, --json on every command,
the debug traceback, output that is not a terminal."""

from __future__ import annotations

import json
import re

import pytest

from prop_cli import constants as C
from tests.cli.shares import assert_clean_error, personalize


def test_help_lists_commands(cli):
    res = cli("--help")
    assert res.code == 0
    for cmd in ("keygen", "inspect", "personalize", "run"):
        assert cmd in res.out


def test_version_names_the_distribution(cli):
    from importlib.metadata import version

    res = cli("--version")
    assert res.code == 0 and res.out.strip() == f"{C.DISTRIBUTION} {version(C.DISTRIBUTION)}"
    assert C.DISTRIBUTION != "prop-cli"  # someone else's package on the registry


def test_debug_env_shows_traceback(cli, workdir, monkeypatch):
    monkeypatch.setenv(C.ENV_DEBUG, "1")
    from prop_cli.errors import PropError

    with pytest.raises(PropError):
        cli("inspect", workdir / "nope.safetensors")


def test_output_that_is_not_a_terminal_is_neither_wrapped_nor_split(cli, workdir):
    """Fix 9: piped output wrapped at 80 columns and split table cells; personalize showed no progress."""
    deep = workdir / ("a_directory_name_long_enough_to_push_the_title_past_eighty_columns_" * 2)
    deep.mkdir()
    res = personalize(cli, workdir, "--steps", "20", out=deep / "b.prop")
    assert res.code == 0, res.err
    steps = [ln for ln in res.err.splitlines() if ln.startswith("personalize: step ")]
    assert steps[0].startswith("personalize: step 2/20") and steps[-1].startswith("personalize: step 20/20")
    assert any(str(deep / "b.prop") in ln for ln in res.out.splitlines())  # the path on one line
    res = cli("attack", deep / "b.prop", "--data", workdir / "mine.npz", "--key-file", workdir / "k.bin",
              "--hamming", "1", "--random", "16", "--restarts", "2", "--search-steps", "5",
              "--blackbox", "256")  # fmt: skip
    assert res.code == 0, res.err
    lines = res.out.splitlines()
    assert any(f"audit of {deep / 'b.prop'} (regression" in ln for ln in lines)
    rows = [ln.split() for ln in lines if ln.strip().startswith(("T0 ", "T1 ", "T2 "))]
    assert [r[:2] for r in rows[:3]] == [["T0", "null"], ["T0", "random"], ["T0", "hamming"]]
    assert all(len(r) >= 5 for r in rows)  # every cell of a row on the row's line


def test_every_command_has_json(cli):
    """Fix 12: the README says every command has --json; run and keygen had none."""
    from prop_cli.cli.main import app

    for cmd in app.registered_commands:
        res = cli(cmd.name, "--help")
        assert "--json" in res.out, cmd.name


def test_every_help_reads_as_a_user_types_it(cli):
    """No typer artefacts: {checkpoint}, <list[Path]>, a count's "[default: 0]"; arguments by the
    upper-case names the help texts use (CHECKPOINT, BUNDLE)."""
    from prop_cli.cli.main import app

    # 0 says something there (--hard-negatives 0: off)
    meaningful_zero = {"--threads", "--seed", "--noise-seed", "--max-steps", "--hard-negatives"}
    for cmd in app.registered_commands:
        res = cli(cmd.name, "--help")
        assert res.code == 0, cmd.name
        usage = res.out.splitlines()[0]
        assert "{" not in res.out and "<list" not in res.out, (cmd.name, res.out)
        assert "[default: None]" not in res.out and "[default: False]" not in res.out, cmd.name
        options = re.split(r"\n  (?=-)", res.out.split("\nOptions:\n")[-1])  # one entry per option
        for entry in options:
            if "[default: 0]" in " ".join(entry.split()):
                assert entry.split()[0] in meaningful_zero, (cmd.name, entry)
        words = usage.split()[3:]  # Usage: prop CMD [OPTIONS] ARGS...
        assert all(w.isupper() for w in words), usage
    personalize_help = cli("personalize", "--help").out
    assert personalize_help.startswith("Usage: prop personalize [OPTIONS] CHECKPOINT\n")
    assert "--data <path>..." in personalize_help and "--key-file <path>..." in personalize_help
    assert "Usage: prop push [OPTIONS] BUNDLE REPO" in cli("push", "--help").out
    assert "Missing argument 'CHECKPOINT'" in cli("inspect").err


def test_run_and_keygen_json(cli, workdir):
    res = cli("keygen", workdir / "new.bin", "--json")
    assert res.code == 0 and json.loads(res.out) == {
        "bits": 128,
        "mode": "0600",
        "path": str(workdir / "new.bin"),
    }
    assert personalize(cli, workdir).code == 0
    res = cli(
        "run", workdir / "mine.prop", "--input", workdir / "x.npy", "--output", workdir / "y.npy", "--json"
    )
    assert res.code == 0 and json.loads(res.out)["shape"] == [8, 2]


@pytest.mark.parametrize(
    "args, words",
    [
        (["run", "b.prop", "--input", "x.npy"], "Missing option '--output'; see prop run --help"),
        (["personalize", "m.safetensors", "--bogus"], "No such option: --bogus"),
    ],
)
def test_usage_errors_are_one_prop_error_line(cli, args, words):
    res = cli(*args)
    assert_clean_error(res, words)
    assert "Usage:" not in res.err and "Try '" not in res.err
