"""What a new user met first (issue 41, the newcomer list): each item as the user typed it."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import FAST, make_mlp_checkpoint

LONG = "policy_network.feature_extractor.layers."  # keyed-layer names long enough to pass 100 columns


@pytest.fixture
def long_bundle(workdir, cli):
    """A 13-layer MLP whose 12 keyed layers' names make a ~550-character keyed-layers row."""
    make_mlp_checkpoint(workdir / "long.safetensors", sizes=(4, *[16] * 12, 2), prefix=LONG)
    r = cli("personalize", workdir / "long.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "long.prop", "--steps", "5", "--device", "cpu")  # fmt: skip
    assert r.code == 0, r.err
    return workdir / "long.prop"


@pytest.mark.parametrize("what", ["long.prop", "long.safetensors"])
def test_inspect_wraps_to_columns(long_bundle, cli, monkeypatch, what):
    monkeypatch.setenv("COLUMNS", "100")
    r = cli("inspect", long_bundle.parent / what)
    assert r.code == 0, r.err
    lines = r.out.splitlines()
    assert max(len(line.rstrip()) for line in lines) <= 100, r.out
    # Wrapped, not cut: every keyed layer's name is there in full.
    text = "".join(line.replace("│", "").replace(" ", "") for line in lines)
    for i in range(2, 25, 2):
        assert f"{LONG}{i}" in text


def test_inspect_without_columns_keeps_each_row_on_one_line(long_bundle, cli, monkeypatch):
    monkeypatch.delenv("COLUMNS", raising=False)  # piped, nothing asked: one line per row (for grep)
    r = cli("inspect", long_bundle)
    row = [line for line in r.out.splitlines() if "keyed layers" in line]
    assert len(row) == 1 and f"{LONG}2, " in row[0] and f"{LONG}24" in row[0]


def test_a_bundles_manifest_names_its_bundle(workdir, cli, monkeypatch):
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "mine.prop", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    manifest = workdir / "mine.prop" / "manifest.json"
    r = cli("run", manifest, "--input", workdir / "x.npy", "--key-file", workdir / "k.bin", "--output",
            workdir / "y.npy")  # fmt: skip
    assert r.code == 0, r.err
    r2 = cli("run", workdir / "mine.prop", "--input", workdir / "x.npy", "--key-file", workdir / "k.bin",
             "--output", workdir / "y2.npy")  # fmt: skip
    assert r2.code == 0 and np.array_equal(np.load(workdir / "y.npy"), np.load(workdir / "y2.npy"))
    r = cli("inspect", manifest, "--json")
    assert r.code == 0 and '"mode": "unsealed"' in r.out, r.err
    monkeypatch.chdir(workdir / "mine.prop")  # from inside the bundle: manifest.json is "."
    r = cli("run", "manifest.json", "--input", workdir / "x.npy", "--output", workdir / "y0.npy")
    assert r.code == 0, r.err


def test_only_a_manifest_json_file_names_its_folder(workdir, cli):
    """Any other file inside a bundle, or a folder called manifest.json, is not taken for the bundle."""
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "mine.prop", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    (workdir / "manifest.json").mkdir()
    for path in (workdir / "mine.prop" / "base.safetensors", workdir / "manifest.json"):
        r = cli("run", path, "--input", workdir / "x.npy", "--output", workdir / "y.npy")
        assert r.code == 2 and "not a prop bundle" in r.err, r.err


def test_the_library_names_the_folder_to_give(workdir, cli):
    from prop_cli.api import load_bundle
    from prop_cli.errors import PropError

    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "mine.prop", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    with pytest.raises(PropError, match="give the bundle folder .*mine.prop"):
        load_bundle(workdir / "mine.prop" / "manifest.json")


class _Clock:
    """time as prop_cli.cli.common reads it, moved by hand."""

    def __init__(self) -> None:
        self.now = 0.0

    def perf_counter(self) -> float:
        return self.now


def _plain_lines(monkeypatch, capsys, total: int, setup: float, step_s: float) -> list[str]:
    from prop_cli.cli import common

    clock = _Clock()
    monkeypatch.setattr(common, "time", clock)

    def train(callback):
        clock.now = setup
        for step in range(1, total + 1):
            callback(step, {"loss": 1.0})
            clock.now += step_s

    capsys.readouterr()
    common.step_progress(train, total, "personalize", lambda info: f"loss {info['loss']:.1f}")
    return capsys.readouterr().err.splitlines()


def test_progress_lines_say_how_long_is_left(monkeypatch, capsys):
    """Steps left x the mean step time since the first step (the set-up before it not counted)."""
    lines = _plain_lines(monkeypatch, capsys, total=100, setup=30.0, step_s=2.0)
    assert lines[0] == "personalize: step 10/100 (48.0 s, about 3 min 00 s left) loss 1.0"
    assert lines[-1] == "personalize: step 100/100 (228.0 s) loss 1.0"  # done: no estimate
    assert len(lines) == 10


def test_a_slow_run_prints_at_least_once_a_minute(monkeypatch, capsys):
    lines = _plain_lines(monkeypatch, capsys, total=1000, setup=0.0, step_s=30.0)
    assert lines[0].startswith("personalize: step 3/1000 (60.0 s, about 8 h 18 min left)")
    assert len(lines) > 400  # every other step, not only every hundredth


def test_a_real_run_prints_its_estimate(workdir, cli):
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "mine.prop", *FAST)  # fmt: skip
    steps = [line for line in r.err.splitlines() if line.startswith("personalize: step ")]
    assert r.code == 0 and len(steps) == 10 and all(" left) " in line for line in steps[:-1]), r.err


def test_personalize_says_what_it_does_before_the_first_step_and_after_the_last(workdir, cli, monkeypatch):
    """issue 44: what was loaded and the set-up are said before the first step, and writing (with the
    report) after the last, each on one stderr line with the time so far; stdout keeps the results. (A
    stage shows once it has lasted STATUS_AFTER_S; 0 here: every stage.)"""
    from prop_cli.cli import common

    monkeypatch.setattr(common, "STATUS_AFTER_S", 0)
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "said.prop", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    lines = r.err.splitlines()
    said = [i for i, line in enumerate(lines) if line.startswith("personalize: ") and " s)" in line
            and not line.startswith("personalize: step ")]  # fmt: skip
    words = [lines[i] for i in said]
    assert [w.split(":")[1].split()[0] for w in words] == ["loaded", "setting", "writing"], words
    first_step = next(i for i, line in enumerate(lines) if line.startswith("personalize: step "))
    assert said[1] < first_step < said[2]
    assert "personalize: " not in r.out


def test_a_status_shows_only_once_its_stage_has_lasted(monkeypatch, capsys):
    """A short stage (or one ending in an error) says nothing; a long one is said while it runs."""
    import time

    from prop_cli.cli import common

    monkeypatch.setattr(common, "STATUS_AFTER_S", 0.05)
    with common.StatusLines("personalize") as say:
        say("quick")
        say("slow")  # replaces "quick" before it showed
        say.pending.join(5)  # the stage lasts past STATUS_AFTER_S: it shows
        say("cut short")  # the run ends before it shows
    time.sleep(0.15)
    err = capsys.readouterr().err.splitlines()
    assert [line.split(" (")[0] for line in err] == ["personalize: slow"], err


def test_export_peft_names_the_payload_it_needs(workdir, cli):
    """--peft takes a --seal --payload peft-lora bundle only: said before training and in the error."""
    r = cli("personalize", "--help")
    assert "--seal --payload peft-lora" in " ".join(r.out.split()) and "export --peft" in r.out
    r = cli("personalize", workdir / "model.safetensors", "--data", workdir / "mine.npz", "--key-file",
            workdir / "k.bin", "--out", workdir / "mine.prop", *FAST)  # fmt: skip
    assert r.code == 0, r.err
    r = cli("export", workdir / "mine.prop", "--peft", workdir / "adapter", "--key-file", workdir / "k.bin")
    assert r.code == 2 and len(r.err.strip().splitlines()) == 1, r.err
    assert "is unsealed" in r.err and "personalize again with --seal --payload peft-lora" in r.err
    assert not (workdir / "adapter").exists()
