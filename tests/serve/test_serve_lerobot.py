"""prop serve with a LeRobot ACT bundle: openpi-client gets what KeyedPolicy's select_action gives, each
connection with its own action queue (scripts/test-lerobot.sh)."""

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


def test_act_over_openpi_client_matches_keyed_policy_per_connection(act_bundle, start_bundle):
    bundle = load_bundle(act_bundle)
    features = bundle.loaded.policy.config.input_features
    rng = np.random.default_rng(0)
    frames = [{k: rng.uniform(-1, 1, tuple(f.shape)).astype(np.float32) for k, f in features.items()}
              for _ in range(4)]  # fmt: skip
    user, base = KeyedPolicy(bundle, KEY), KeyedPolicy(bundle)
    want_user = [user.select_action(f) for f in frames]
    want_base = [base.select_action(f) for f in frames]
    assert not np.allclose(want_user, want_base, atol=1e-4)
    running = start_bundle(act_bundle)
    keyed = client_policy.WebsocketClientPolicy(host="127.0.0.1", port=running.port,
                                                api_key=np.packbits(KEY).tobytes().hex())  # fmt: skip
    nokey = client_policy.WebsocketClientPolicy(host="127.0.0.1", port=running.port)
    meta = keyed.get_server_metadata()
    assert meta["kind"] == "lerobot" and meta["keyed"] is True and meta["action_horizon"] == 1
    for f, u, b in zip(frames, want_user, want_base):  # interleaved: each connection's queue is its own
        got_u = keyed.infer(f)["actions"]
        got_b = nokey.infer(f)["actions"]
        assert got_u.shape == (1, *u.shape)
        np.testing.assert_allclose(got_u[0], u, rtol=0, atol=1e-5)
        np.testing.assert_allclose(got_b[0], b, rtol=0, atol=1e-5)
    # {"reset": True} starts the connection's episode again: its queue replays the same actions.
    assert keyed.infer({"reset": True}) == {"reset": True}
    for f, u in zip(frames, want_user):
        np.testing.assert_allclose(keyed.infer(f)["actions"][0], u, rtol=0, atol=1e-5)
    # A second no-key connection starts its own episode: the base's queue is not shared with the first.
    late = client_policy.WebsocketClientPolicy(host="127.0.0.1", port=running.port)
    for f, b in zip(frames, want_base):
        np.testing.assert_allclose(late.infer(f)["actions"][0], b, rtol=0, atol=1e-5)
        nokey.infer(f)
    for c in (keyed, nokey, late):
        c._ws.close()
