"""Helpers of the CLI tests: personalize the workdir's model, check a one-line error."""

from __future__ import annotations

from tests.conftest import FAST


def personalize(cli, wd, *extra, out="mine.prop"):
    return cli(
        "personalize",
        wd / "model.safetensors",
        "--data",
        wd / "mine.npz",
        "--key-file",
        wd / "k.bin",
        "--out",
        wd / out,
        *FAST,
        *extra,
    )


# The start of a PNG that matplotlib wrote (its signature, then the "Software" text chunk it adds).
PNG_BY_MATPLOTLIB = b"\x89PNG\r\n\x1a\n\0\0\0\x28tEXtSoftware\0Matplotlib version3.9.0, https://matplotlib.org/"


def assert_clean_error(res, *words):
    assert res.code == 2, (res.code, res.err)
    lines = [ln for ln in res.err.strip().splitlines() if ln.startswith("prop: error:")]
    assert len(lines) == 1, res.err
    assert "Traceback" not in res.err
    for w in words:
        assert w in lines[0], (w, lines[0])


def refused_before_training(res, monkeypatch_calls: list, *words: str) -> None:
    assert_clean_error(res, *words)
    assert "personalize: step" not in res.err and not monkeypatch_calls  # no data read, no step trained
