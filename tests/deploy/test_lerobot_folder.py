"""`prop export --lerobot`: what it refuses, in one line, without LeRobot (tests/plugin runs the folder
in LeRobot's tools)."""

from __future__ import annotations

import pytest

from tests.cli.shares import personalize


@pytest.fixture
def bundle(cli, workdir):
    assert personalize(cli, workdir).code == 0
    return workdir / "mine.prop"


def test_an_array_model_has_no_lerobot_folder(bundle, cli, workdir):
    r = cli("export", bundle, "--lerobot", workdir / "policy")
    assert r.code != 0 and len(r.err.strip().splitlines()) == 1, r.err
    assert "not a LeRobot policy" in r.err and "--onnx" in r.err
    assert not (workdir / "policy").exists()


def test_one_export_format_at_a_time(bundle, cli, workdir):
    r = cli("export", bundle, "--lerobot", workdir / "policy", "--onnx")
    assert r.code != 0 and "choose one export format" in r.err and len(r.err.strip().splitlines()) == 1
    r = cli("export", bundle, "--onnx", "--resize-images")
    assert r.code != 0 and "--resize-images goes with --lerobot" in r.err


def test_a_folder_that_is_not_a_lerobot_folder_is_not_replaced(bundle, cli, workdir):
    mine = workdir / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    r = cli("export", bundle, "--lerobot", mine, "--force")
    assert r.code != 0 and len(r.err.strip().splitlines()) == 1, r.err
    assert (mine / "notes.txt").read_text() == "keep"
    r = cli("export", bundle, "--lerobot", bundle)
    assert r.code != 0 and len(r.err.strip().splitlines()) == 1, r.err
