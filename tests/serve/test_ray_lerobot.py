"""prop serve-ray with LeRobot ACT and SmolVLA bundles on a local Ray instance on the loopback, openpi-client
connecting unchanged: the replicas serve the policy as `prop serve` does (``chunks.ChunkRunner``), each
user routed to a replica that holds it, each connection's episode state kept by the gateway.

Needs lerobot, ray and openpi-client together: .venv-lerobot built with PROP_LEROBOT_RAY=1
(scripts/setup-lerobot.sh; .ci/run does); skipped with the reason otherwise. Slow: a tiny ACT trained and
personalized, a tiny SmolVLA too, and a local Ray instance started twice (~3 min on 2 busy cores)."""

from __future__ import annotations

import json
import signal
import socket

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed

pytest.importorskip("lerobot", reason="prop serve-ray with a LeRobot policy needs lerobot (.venv-lerobot)")
pytest.importorskip("ray.serve", reason="serve-ray needs ray: PROP_LEROBOT_RAY=1 scripts/setup-lerobot.sh")
client_policy = pytest.importorskip("openpi_client.websocket_client_policy")

from examples import lerobot_reach_task as task  # noqa: E402
from prop_cli import api  # noqa: E402
from prop_cli.bundle import load_bundle  # noqa: E402
from prop_cli.config import PersonalizeConfig  # noqa: E402
from prop_cli.core.key_files import KeySource  # noqa: E402
from prop_cli.run import KeyedPolicy  # noqa: E402
from tests.lerobot_bases import act_base, smolvla_base  # noqa: E402
from tests.serve.shares import OPENPI_CONNECT, routed_rounds, start_serve_ray  # noqa: E402

pytestmark = [pytest.mark.lerobot, pytest.mark.slow, OPENPI_CONNECT]
TINY = dict(steps=15, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=4, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip
KEY = np.random.default_rng(1).integers(0, 2, 128).astype(np.uint8)
KEY2 = np.random.default_rng(2).integers(0, 2, 128).astype(np.uint8)
WRONG = np.random.default_rng(3).integers(0, 2, 128).astype(np.uint8)
ATOL = 1e-5  # a batched row against KeyedPolicy's folded weights: float rounding (test_serve_lerobot.py)
MAX_MESSAGE = 2**16  # the deployment's message cap here: an ACT frame (state only) is ~100 bytes


def _hex(key: np.ndarray) -> str:
    return np.packbits(key).tobytes().hex()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _client(port: int, key: np.ndarray | None = None):
    return client_policy.WebsocketClientPolicy(host="127.0.0.1", port=port,
                                               api_key=_hex(key) if key is not None else None)  # fmt: skip


def _frames(bundle, n: int, seed: int = 0) -> list[dict]:
    features = bundle.loaded.policy.config.input_features
    rng = np.random.default_rng(seed)
    return [{k: rng.uniform(-1, 1, tuple(f.shape)).astype(np.float32) for k, f in features.items()}
            for _ in range(n)]  # fmt: skip


def _alone(bundle, key, frame) -> np.ndarray:
    """KeyedPolicy's chunk for ``frame`` on a fresh episode: what `prop serve` answers (its own tests)."""
    policy = KeyedPolicy(bundle, key)
    policy.reset()
    return policy.controller.action_chunk(frame)


@pytest.fixture(scope="module")
def act_dir(tmp_path_factory):
    """A tiny ACT (tests/lerobot_bases.py), personalized unsealed for KEY and sealed (LoRA) for KEY, KEY2."""
    d = tmp_path_factory.mktemp("ray-lerobot")
    act_base(d)
    task.record(d / "user2", 3, 60_000, -task.USER_OFFSET)
    api.personalize_checkpoint(str(d / "act"), [(d / "user", KeySource(KEY, "file"))], d / "unsealed",
                               PersonalizeConfig.of(**TINY), general=d / "general")  # fmt: skip
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "payload": "lora", "payload_rank": 2}))
    api.personalize_checkpoint(
        str(d / "act"), [(d / "user", KeySource(KEY, "file")), (d / "user2", KeySource(KEY2, "file"))],
        d / "sealed", cfg,
    )  # fmt: skip
    return d


def test_prop_serve_ray_serves_an_unsealed_act_bundle_until_sigterm(act_dir):
    """The CLI end to end (before the module's own Ray instance starts): its URL on stdout, ACT's chunk for
    a user's key and for no key through openpi-client, SIGTERM stops it cleanly, the key nowhere."""
    bundle = load_bundle(act_dir / "unsealed")
    frame = _frames(bundle, 1, seed=4)[0]
    want = {"user": _alone(bundle, KEY, frame), "base": _alone(bundle, None, frame)}
    assert not np.allclose(want["user"], want["base"], atol=1e-4)  # the key changes the chunk
    port = _free_port()
    proc, line = start_serve_ray(act_dir / "unsealed", port)
    try:
        assert json.loads(line)["url"] == f"ws://127.0.0.1:{port}", (line, proc.stderr.read())
        user, base = _client(port, KEY), _client(port, None)
        meta = user.get_server_metadata()
        assert meta["kind"] == "lerobot" and meta["keyed"] is True
        assert meta["action_horizon"] == want["user"].shape[0] > 1
        assert base.get_server_metadata()["keyed"] is False
        np.testing.assert_allclose(user.infer(frame)["actions"], want["user"], rtol=0, atol=ATOL)
        np.testing.assert_array_equal(base.infer(frame)["actions"], want["base"])  # the original's, exactly
        for c in (user, base):
            c._ws.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "stopped" in err and "Traceback" not in err, err
    assert _hex(KEY) not in err


def test_a_policy_with_state_on_its_module_is_refused_before_ray_starts(act_dir):
    """ACT with temporal ensembling answers one action at a time from its module's own queue: a connection
    would have to stay on one replica. application() refuses it in one line, before anything is deployed."""
    from prop_cli.errors import PropError
    from prop_cli.serve.ray_app import application

    bundle = load_bundle(act_dir / "unsealed")
    application(act_dir / "unsealed", bundle=bundle)  # plain ACT: servable (nothing deployed yet)
    from lerobot.policies.act.modeling_act import ACTTemporalEnsembler

    module = bundle.loaded.module  # made as ACTPolicy makes it with temporal_ensemble_coeff set
    module.config.temporal_ensemble_coeff = 0.01
    module.temporal_ensembler = ACTTemporalEnsembler(0.01, module.config.chunk_size)
    with pytest.raises(PropError) as e:
        application(act_dir / "unsealed", bundle=bundle)
    what = e.value.what
    assert "the act policy in" in what and "keeps state on its module" in what and "\n" not in str(e.value)
    assert e.value.fix == "serve it with prop serve"


@pytest.fixture(scope="module")
def ray_served(act_dir):
    """The sealed two-user ACT deployed on a local Ray instance on a free loopback port: 2 replicas, each
    holding at most 1 user, so a user served by a replica that already holds it shows routing at work."""
    import ray
    from ray import serve

    from prop_cli.serve.ray_app import APP_NAME, application

    port = _free_port()
    ray.init(address="local", include_dashboard=False, num_cpus=2, log_to_driver=False)
    try:
        serve.start(http_options={"host": "127.0.0.1", "port": port})
        app = application(act_dir / "sealed", replicas=2, users_per_replica=1, replica_cpus=0.5,
                          max_message_bytes=MAX_MESSAGE)  # fmt: skip
        serve.run(app, name=APP_NAME, route_prefix="/")
        yield act_dir / "sealed", port
    finally:
        serve.shutdown()
        ray.shutdown()


def test_users_and_no_key_through_ray_equal_prop_serve(ray_served):
    path, port = ray_served
    bundle = load_bundle(path)
    frames = _frames(bundle, 2, seed=5)
    keys = {"a": KEY, "b": KEY2, "-": None}
    want = {name: [_alone(bundle, k, f) for f in frames] for name, k in keys.items()}
    assert not np.allclose(want["a"][0], want["b"][0], atol=1e-4)
    assert not np.allclose(want["a"][0], want["-"][0], atol=1e-4)
    clients = {name: _client(port, k) for name, k in keys.items()}
    for name, c in clients.items():
        meta = c.get_server_metadata()
        assert meta["kind"] == "lerobot" and meta["keyed"] is (name != "-")
        assert meta["action_horizon"] == want[name][0].shape[0]
        assert meta["observation"] == list(bundle.loaded.policy.input_features)
    worst = 0.0
    for i, f in enumerate(frames):  # interleaved: each user's own behaviour every time
        for name, c in clients.items():
            got = c.infer(f)["actions"]
            assert got.shape == want[name][i].shape and got.dtype == np.float32
            if name == "-":  # no key: the original's chunk bit for bit (run alone, as prop serve runs it)
                np.testing.assert_array_equal(got, want[name][i])
            else:
                worst = max(worst, float(np.abs(got - want[name][i]).max()))
    print(f"ACT sealed through Ray: worst {worst:.2e}")
    assert worst <= ATOL, worst
    # A batch of frames (N, ...) answers (N, steps, dim), as prop serve does.
    batch = {k: np.stack([f[k] for f in frames]) for k in frames[0]}
    got = clients["a"].infer(batch)["actions"]
    np.testing.assert_allclose(got, np.stack(want["a"]), rtol=0, atol=ATOL)
    for c in clients.values():
        c._ws.close()


def test_a_wrong_key_and_bad_messages_are_refused_in_one_line(ray_served):
    path, port = ray_served
    with pytest.raises(ConnectionClosed) as e:
        _client(port, WRONG)
    reason = e.value.rcvd.reason
    assert e.value.rcvd.code == 1008 and reason.startswith("refused:") and "enrolled in nothing" in reason
    assert str(path.parent) not in reason and _hex(WRONG) not in reason
    ok = _client(port, KEY)  # the others are served
    frame = _frames(load_bundle(path), 1)[0]
    with pytest.raises(RuntimeError, match="prop serve: error: the observation has no") as e:
        ok.infer({"nothing": np.zeros(3, np.float32)})  # a one-line error; the connection goes on
    assert "\n" not in str(e.value).split("Error in inference server:")[-1].strip()
    with pytest.raises(RuntimeError, match="a reset's seed is an int, not str"):
        ok.infer({"reset": True, "seed": "three"})
    assert ok.infer(frame)["actions"].ndim == 2
    with pytest.raises(ConnectionClosed) as e:  # a message over the cap closes this connection only
        ok.infer(frame | {"pad": np.zeros(MAX_MESSAGE, np.uint8)})
        ok.infer(frame)
    assert e.value.rcvd.code == 1009, e.value.rcvd
    again = _client(port, KEY)
    assert again.infer(frame)["actions"].ndim == 2
    again._ws.close()


def test_the_same_user_lands_on_the_replica_that_holds_it(ray_served):
    path, port = ray_served
    frame = _frames(load_bundle(path), 1)[0]
    users = {"a": KEY, "b": KEY2}
    rounds = routed_rounds(lambda key: _client(port, key), users, frame)
    for name in users:
        assert {r[name] for r in rounds} == {(rounds[0][name][0], True)}, (name, rounds)
    assert rounds[0]["a"][0] != rounds[0]["b"][0]  # one user a replica (each holds one at most)


def test_a_reset_starts_that_connections_episode_only(ray_served):
    """A connection's episode (its seed, its calls: the noise seeds of a sampling policy) is the gateway's,
    sent with each request; the replica answers with it advanced. Checked on the replica's own handle (ACT
    samples no noise, so its chunks cannot show it), and over openpi-client: a reset on one connection
    leaves another of the same user where it was."""
    from ray import serve

    from prop_cli.serve.ray_app import APP_NAME
    from prop_cli.serve.route import route_salt, routing_id
    from prop_cli.serve.wire import packb, unpackb

    path, port = ray_served
    bundle = load_bundle(path)
    frame = _frames(bundle, 1, seed=6)[0]
    handle = serve.get_deployment_handle("PolicyReplica", app_name=APP_NAME)
    handle = handle.options(multiplexed_model_id=routing_id(KEY, route_salt(bundle.manifest)))
    reply, episode = handle.infer.remote(_hex(KEY), packb(frame), (7, 2)).result()
    assert episode == (7, 3)  # a chunk: one call more in the same episode
    np.testing.assert_allclose(unpackb(reply)["actions"], _alone(bundle, KEY, frame), rtol=0, atol=ATOL)
    reply, episode = handle.infer.remote(_hex(KEY), packb({"reset": True, "seed": 5}), (7, 3)).result()
    assert unpackb(reply) == {"reset": True} and episode == (5, 0)  # a new episode, no call yet
    reply, episode = handle.infer.remote(_hex(KEY), packb({"reset": True}), (5, 4)).result()
    assert episode == (0, 0)
    reply, episode = handle.infer.remote(_hex(KEY), packb({"nothing": 1}), (5, 4)).result()
    assert reply.startswith("prop serve: error:") and episode == (5, 4)  # refused: not counted

    one, two = _client(port, KEY), _client(port, KEY)
    for c in (one, two):
        c.infer(frame)
    assert one.infer({"reset": True, "seed": 3}) == {"reset": True}
    for c in (one, two):  # both go on, each in its own episode
        np.testing.assert_allclose(c.infer(frame)["actions"], _alone(bundle, KEY, frame), rtol=0, atol=ATOL)
    for c in (one, two):
        c._ws.close()


@pytest.fixture(scope="module")
def smolvla_sealed(tmp_path_factory):
    """A tiny SmolVLA (examples/smolvla_tiny.py) sealed for KEY (LoRA payload), as test_serve_lerobot.py's."""
    pytest.importorskip("num2words", reason="SmolVLM's processor needs num2words")
    d = tmp_path_factory.mktemp("ray-smolvla")
    smolvla_base(d)
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "steps": 10, "payload": "lora", "payload_rank": 2}))
    api.personalize_checkpoint(str(d / "smolvla"), [(d / "user", KeySource(KEY, "file"))], d / "sealed", cfg)
    return d / "sealed"


SMOLVLA_ATOL = 1e-4  # test_serve_lerobot.py's SmolVLA tolerance (its LoRA rows against the folded weights)


def test_smolvla_episodes_are_each_connections_own(ray_served, smolvla_sealed):
    """A sampling policy shows the episode state: each call of an episode draws its own noise, so two
    connections of one user each get call 1's chunk, then call 2's; a reset with a seed starts that
    connection's new episode and leaves the other where it was. Runs last: it replaces the module's
    ACT application with the SmolVLA one (2 replicas, the same Ray instance)."""
    from ray import serve

    from prop_cli.serve.ray_app import APP_NAME, application

    _, port = ray_served
    serve.run(application(smolvla_sealed, replicas=2, users_per_replica=1, replica_cpus=0.5), name=APP_NAME,
              route_prefix="/")  # fmt: skip
    bundle = load_bundle(smolvla_sealed)
    frame = _frames(bundle, 1, seed=9)[0] | {"task": "reach the goal"}

    def episode(key, seed: int, calls: int) -> list[np.ndarray]:
        policy = KeyedPolicy(bundle, key)
        policy.reset(seed=seed)
        return [policy.controller.action_chunk(frame) for _ in range(calls)]

    user, base, new = episode(KEY, 0, 2), episode(None, 0, 2), episode(KEY, 3, 1)[0]
    assert not np.allclose(user[0], user[1], atol=1e-3)  # each call draws its own noise
    assert not np.allclose(new, user[0], atol=1e-3)  # and each episode
    one, two, nokey = _client(port, KEY), _client(port, KEY), _client(port, None)
    assert one.get_server_metadata()["kind"] == "lerobot"

    def close(client, want) -> None:
        np.testing.assert_allclose(client.infer(frame)["actions"], want, rtol=0, atol=SMOLVLA_ATOL)

    close(one, user[0])
    close(two, user[0])
    close(one, user[1])
    assert one.infer({"reset": True, "seed": 3}) == {"reset": True}
    close(one, new)  # one: its new episode's first call
    close(two, user[1])  # two: its own episode's second call, untouched by one's reset
    for want in base:  # no key: the original's chunks, each call's noise, bit for bit
        np.testing.assert_array_equal(nokey.infer(frame)["actions"], want)
    for c in (one, two, nokey):
        c._ws.close()
