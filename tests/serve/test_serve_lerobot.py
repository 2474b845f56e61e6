"""prop serve with a LeRobot ACT bundle: openpi-client gets ACT's whole action chunk per infer, what
n_action_steps of KeyedPolicy's select_action give, for each connection's key (scripts/test-lerobot.sh)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("lerobot")
client_policy = pytest.importorskip("openpi_client.websocket_client_policy")

from examples import lerobot_reach_task as task  # noqa: E402
from prop_cli import api  # noqa: E402
from prop_cli.bundle import load_bundle  # noqa: E402
from prop_cli.config import PersonalizeConfig  # noqa: E402
from prop_cli.core.key_files import KeySource  # noqa: E402
from prop_cli.run import KeyedPolicy  # noqa: E402
from tests.serve.shares import OPENPI_CONNECT  # noqa: E402

pytestmark = [pytest.mark.lerobot, OPENPI_CONNECT]
TINY = dict(steps=15, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=4, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip
KEY = np.random.default_rng(1).integers(0, 2, 128).astype(np.uint8)


@pytest.fixture(scope="module")
def act_bundle(tmp_path_factory):
    d = tmp_path_factory.mktemp("serve-lerobot")
    task.record(d / "general", 4, 0, np.zeros(3, np.float32))
    task.record(d / "user", 3, 50_000, task.USER_OFFSET)
    task.train_base(d / "general", d / "act", steps=5)
    api.personalize_checkpoint(
        str(d / "act"), [(d / "user", KeySource(KEY, "file"))], d / "bundle", PersonalizeConfig.of(**TINY),
        general=d / "general",
    )  # fmt: skip
    return d / "bundle"


def test_act_answers_its_whole_chunk_per_connection(act_bundle, start_bundle):
    """openpi clients take a chunk per infer: ACT's chunk is what n_action_steps select_action calls give."""
    bundle = load_bundle(act_bundle)
    features = bundle.loaded.policy.config.input_features
    rng = np.random.default_rng(0)
    frames = [{k: rng.uniform(-1, 1, tuple(f.shape)).astype(np.float32) for k, f in features.items()}
              for _ in range(2)]  # fmt: skip
    user, base = KeyedPolicy(bundle, KEY), KeyedPolicy(bundle)
    steps = user.controller.chunk_steps
    assert steps is not None and steps > 1
    want = {}
    for name, policy in (("user", user), ("base", base)):
        chunks = []
        for f in frames:
            policy.reset()
            chunks.append(np.stack([policy.select_action(f) for _ in range(steps)]))
        want[name] = chunks
    assert not np.allclose(want["user"][0], want["base"][0], atol=1e-4)
    running = start_bundle(act_bundle)
    keyed = client_policy.WebsocketClientPolicy(host="127.0.0.1", port=running.port,
                                                api_key=np.packbits(KEY).tobytes().hex())  # fmt: skip
    nokey = client_policy.WebsocketClientPolicy(host="127.0.0.1", port=running.port)
    assert keyed.get_server_metadata()["action_horizon"] == steps
    for i, f in enumerate(frames):
        got_u, got_b = keyed.infer(f)["actions"], nokey.infer(f)["actions"]
        assert got_u.shape == want["user"][i].shape
        np.testing.assert_allclose(got_u, want["user"][i], rtol=0, atol=1e-5)
        np.testing.assert_allclose(got_b, want["base"][i], rtol=0, atol=1e-5)
    assert keyed.infer({"reset": True}) == {"reset": True}
    for c in (keyed, nokey):
        c._ws.close()
