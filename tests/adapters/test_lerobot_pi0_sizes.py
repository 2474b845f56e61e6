"""A pi0 at a size LeRobot does not build (issue 41, the newcomer list): LeRobot builds pi0 and pi0.5 at
PaliGemma's sizes only, so a tiny one from examples/pi_tiny.py loads only under its patch. Outside it,
prop says that in one line (and how to run it), not that the bundle is damaged."""

from __future__ import annotations

import os
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("lerobot")
pytestmark = pytest.mark.lerobot

from examples import lerobot_reach_task as task  # noqa: E402
from examples import pi_tiny  # noqa: E402
from prop_cli import api  # noqa: E402
from prop_cli.config import PersonalizeConfig  # noqa: E402
from prop_cli.core.key_files import KeySource  # noqa: E402
from prop_cli.errors import PropError  # noqa: E402

TINY = dict(steps=2, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=2, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A tiny pi0 folder and a bundle of it, both made under the example's patch."""
    d = tmp_path_factory.mktemp("pi-sizes")
    task.record(d / "data", 2, 0, np.zeros(3, np.float32), camera=True)
    bits = np.random.default_rng(1).integers(0, 2, 32).astype(np.uint8)
    (d / "k.bin").write_bytes(np.packbits(bits).tobytes())
    (d / "k.bin").chmod(0o600)
    with pi_tiny.tiny():
        built = pi_tiny.build_pi("pi0", pi_tiny.build_tokenizer(d / "tok"), task.dataset_stats(d / "data"))
        task.train_base(d / "data", d / "pi0", steps=1, built=built)
        api.personalize_checkpoint(str(d / "pi0"), [(d / "data", KeySource(bits, "file"))], d / "b.prop",
                                   PersonalizeConfig.of(**TINY))  # fmt: skip
    return d


def _says_what_is_needed(r) -> None:
    assert r.code == 2 and len(r.err.strip().splitlines()) == 1, r.err
    assert "the pi0's language model is 64 wide" in r.err and "PaliGemma's sizes only" in r.err
    assert "python -m examples.pi_tiny ARGS" in r.err
    assert "restore the bundle" not in r.err and "belong together" not in r.err


def test_a_tiny_pi0_outside_the_patch_says_what_it_needs(work, cli):
    _says_what_is_needed(cli("run", work / "b.prop", "--input", work / "data", "--output", work / "y.npy"))
    _says_what_is_needed(cli("inspect", work / "pi0"))
    assert not (work / "y.npy").exists()


def test_the_named_command_runs_it_from_another_folder(work, tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | {"OMP_NUM_THREADS": "1"}
    r = subprocess.run(
        [sys.executable, "-m", "examples.pi_tiny", "run", str(work / "b.prop"), "--input", str(work / "data"),
         "--key-file", str(work / "k.bin"), "--output", "y.npy"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert np.load(tmp_path / "y.npy").shape[0] == 2 * task.HORIZON and "(keyed)" in r.stderr


def test_a_width_of_the_other_variant_names_the_variant():
    from lerobot.policies.pi0.modeling_pi0 import PI0Policy

    from prop_adapters.lerobot.pi0 import GEMMA_WIDTHS, check_sizes

    config = SimpleNamespace(paligemma_variant="gemma_300m", action_expert_variant="gemma_300m")
    shapes = {GEMMA_WIDTHS[0][2]: (257_152, 2048), GEMMA_WIDTHS[1][2]: (2048, 1024)}
    with pytest.raises(PropError, match="is 2048 wide, config.json's paligemma_variant gemma_300m 1024") as e:
        check_sizes(PI0Policy, config, shapes, "m", "pi0")
    assert e.value.fix == "set paligemma_variant to gemma_2b in config.json"
    check_sizes(PI0Policy, SimpleNamespace(paligemma_variant="gemma_2b", action_expert_variant="gemma_300m"),
                shapes, "m", "pi0")  # fmt: skip
