"""Fixtures of the CLI tests: a personalized bundle, a trainer that must not be reached."""

from __future__ import annotations

import pytest

from tests.cli.shares import personalize


@pytest.fixture
def bundle(cli, workdir):
    assert personalize(cli, workdir).code == 0
    return workdir / "mine.prop"


@pytest.fixture
def no_training(monkeypatch) -> list:
    """Record any call to personalize's data loading and trainer: a refusal must come before both."""
    import prop_cli.api as api

    calls: list = []
    monkeypatch.setattr(api, "load_data", lambda *a, **kw: calls.append("load_data"))
    monkeypatch.setattr(api, "personalize", lambda *a, **kw: calls.append("personalize"))
    return calls
