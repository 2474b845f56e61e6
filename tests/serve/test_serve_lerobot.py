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
from tests.lerobot_bases import act_base, diffusion_base, smolvla_base  # noqa: E402
from tests.serve.shares import OPENPI_CONNECT  # noqa: E402

pytestmark = [pytest.mark.lerobot, OPENPI_CONNECT]
TINY = dict(steps=15, user_rows=8, null_rows=4, neighbour_keys=2, random_keys=2, samples_per_key=1,
            eval_random_keys=4, null_weight=2.0, base_lr_scale=0.1)  # fmt: skip
KEY = np.random.default_rng(1).integers(0, 2, 128).astype(np.uint8)


@pytest.fixture(scope="module")
def act_bundle(tmp_path_factory):
    d = tmp_path_factory.mktemp("serve-lerobot")
    act_base(d)
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


# Batched rows against each key's own KeyedPolicy chunk: (W diag d) x against W (d x), B (A x) against
# (W + B A) x, over a larger batch, and ACT's (S, B, D) attention summed over more rows. Measured here
# (float32, CPU): see the print of each test; held under 1e-5.
ATOL = 1e-5
KEY2 = np.random.default_rng(2).integers(0, 2, 128).astype(np.uint8)
WRONG = np.random.default_rng(3).integers(0, 2, 128).astype(np.uint8)


@pytest.fixture(scope="module")
def sealed_act(act_bundle, tmp_path_factory):
    """ACT sealed (LoRA payloads) for two users, KEY and KEY2."""
    d = act_bundle.parent
    if not (d / "user2").exists():
        task.record(d / "user2", 3, 60_000, -task.USER_OFFSET)
    out = tmp_path_factory.mktemp("serve-lerobot-sealed") / "bundle"
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "payload": "lora", "payload_rank": 2}))
    api.personalize_checkpoint(
        str(d / "act"), [(d / "user", KeySource(KEY, "file")), (d / "user2", KeySource(KEY2, "file"))], out,
        cfg,
    )  # fmt: skip
    return out


def _frames(bundle, n: int, seed: int = 0) -> list[dict]:
    features = bundle.loaded.policy.config.input_features
    rng = np.random.default_rng(seed)
    return [{k: rng.uniform(-1, 1, tuple(f.shape)).astype(np.float32) for k, f in features.items()}
            for _ in range(n)]  # fmt: skip


def _alone(bundle, key, frame, allow=False) -> np.ndarray:
    """What KeyedPolicy's controller gives for ``frame`` on a fresh episode (the first call's noise)."""
    policy = KeyedPolicy(bundle, key, allow_unenrolled=allow)
    policy.reset()
    return policy.controller.action_chunk(frame)


@pytest.mark.parametrize("sealed", [False, True])
def test_mixed_users_share_one_forward_and_equal_their_own_runs(sealed, act_bundle, sealed_act):
    from prop_cli.serve.cache import BehaviourCache
    from prop_cli.serve.chunks import batchable
    from prop_cli.serve.rows import Deltas
    from prop_cli.serve.sessions import Session, chunk_runner, payload_table

    bundle = load_bundle(sealed_act if sealed else act_bundle)
    assert batchable(bundle)
    runner, cache = chunk_runner(bundle, payload_table(bundle)), BehaviourCache(2**26)
    assert runner.axes.get("model.encoder.layers.0.linear1") == 1  # ACT's encoder is sequence-first
    who = [KEY, None, KEY2, WRONG, KEY] if sealed else [KEY, None, WRONG, KEY]
    sessions = [Session(bundle, k, True, cache, runner) for k in who]
    if sealed:
        from prop_cli.core.payload import Payload

        assert isinstance(sessions[0].behaviour, Payload) and sessions[0].behaviour is sessions[4].behaviour
        assert sessions[2].behaviour is not sessions[0].behaviour
    else:
        assert isinstance(sessions[0].behaviour, Deltas)
    assert sessions[1].behaviour is None and sessions[3 if sealed else 2].behaviour is None
    frames = _frames(bundle, len(who))
    before = runner.batches
    got = runner.run([s.chunk_request(f) for s, f in zip(sessions, frames)])
    # One forward of the base for every user's rows, and each no-key request (no key, WRONG) its own.
    assert runner.batches == before + 3
    worst = 0.0
    for k, f, y in zip(who, frames, got):
        want = _alone(bundle, k, f, allow=True)
        assert y.shape == want.shape == (runner.steps, want.shape[-1])
        worst = max(worst, float(np.abs(y - want).max()))
        if k is None or k is WRONG:  # no key among users' rows: the original's chunk bit for bit
            np.testing.assert_array_equal(y, want)
            np.testing.assert_array_equal(y, _alone(bundle, None, f))
        else:
            assert not np.allclose(want, _alone(bundle, None, f), atol=1e-4)  # the key changes the chunk
    print(f"ACT {'sealed' if sealed else 'unsealed'}: worst {worst:.2e}")
    assert worst <= ATOL, worst
    # --batch-no-key: the no-key rows join the users' forward, within float rounding of the original.
    batched = chunk_runner(bundle, payload_table(bundle), batch_no_key=True)
    before = batched.batches
    got = batched.run([s.chunk_request(f) for s, f in zip(sessions, frames)])
    assert batched.batches == before + 1
    nokey = max(float(np.abs(y - _alone(bundle, None, f)).max())
                for k, f, y in zip(who, frames, got) if k is None or k is WRONG)  # fmt: skip
    print(f"ACT {'sealed' if sealed else 'unsealed'} --batch-no-key: no-key rows {nokey:.2e}")
    assert nokey <= ATOL, nokey


def test_concurrent_clients_of_two_users_are_batched_over_openpi(sealed_act, start_bundle):
    import concurrent.futures as cf

    bundle = load_bundle(sealed_act)
    frames = _frames(bundle, 1, seed=5)
    want = {name: _alone(bundle, k, frames[0]) for name, k in (("a", KEY), ("b", KEY2), ("-", None))}
    running = start_bundle(sealed_act, batch_window_ms=30)
    Client = client_policy.WebsocketClientPolicy
    clients = [(name, Client(host="127.0.0.1", port=running.port,
                             api_key=np.packbits(k).tobytes().hex() if k is not None else None))
               for name, k in (("a", KEY), ("b", KEY2), ("-", None), ("a", KEY))]  # fmt: skip
    assert clients[0][1].get_server_metadata()["action_horizon"] == running.server.runner.steps
    before = running.server.batcher.batches
    with cf.ThreadPoolExecutor(len(clients)) as pool:
        for _ in range(2):
            outs = list(pool.map(lambda c: c[1].infer({"reset": True}) and c[1].infer(frames[0]), clients))
            for (name, _), y in zip(clients, outs):
                np.testing.assert_allclose(y["actions"], want[name], rtol=0, atol=ATOL)
    assert running.server.batcher.batches - before < 2 * len(clients)  # users shared forwards
    for _, c in clients:
        c._ws.close()


@pytest.fixture(scope="module")
def smolvla_sealed(tmp_path_factory):
    """A tiny SmolVLA (examples/smolvla_tiny.py) sealed for KEY (LoRA payload)."""
    pytest.importorskip("num2words")  # SmolVLM's processor needs it
    d = tmp_path_factory.mktemp("serve-smolvla")
    smolvla_base(d)
    cfg = PersonalizeConfig.of(**(TINY | {"seal": True, "steps": 10, "payload": "lora", "payload_rank": 2}))
    api.personalize_checkpoint(str(d / "smolvla"), [(d / "user", KeySource(KEY, "file"))], d / "sealed", cfg)
    return d / "sealed"


def test_smolvla_rows_of_users_share_a_forward_each_with_its_own_noise(smolvla_sealed):
    """A VLA samples its chunk: each row's noise is drawn from its connection's own seed, so a batched
    row is the chunk its connection gets alone; instructions of other lengths run as their own forward."""
    from prop_cli.serve.cache import BehaviourCache
    from prop_cli.serve.chunks import batchable
    from prop_cli.serve.sessions import Session, chunk_runner, payload_table

    bundle = load_bundle(smolvla_sealed)
    assert batchable(bundle)
    runner, cache = chunk_runner(bundle, payload_table(bundle)), BehaviourCache(2**26)
    who = [KEY, None, WRONG, KEY, None]
    tasks = ["reach the goal"] * 4 + ["go to the red target now"]
    sessions = [Session(bundle, k, True, cache, runner) for k in who]
    for i, s in enumerate(sessions):  # episodes of their own: different noise on every connection
        s.reset(seed=i)
    frames = [f | {"task": t} for f, t in zip(_frames(bundle, len(who), seed=9), tasks)]
    before = runner.batches
    got = runner.run([s.chunk_request(f) for s, f in zip(sessions, frames)])
    assert runner.batches == before + 4  # the users' rows in one forward; each no-key request its own
    worst = 0.0
    for i, (k, f, y) in enumerate(zip(who, frames, got)):
        policy = KeyedPolicy(bundle, k, allow_unenrolled=True)
        policy.reset(seed=i)
        want = policy.controller.action_chunk(f)
        assert y.shape == want.shape == (runner.steps, want.shape[-1])
        worst = max(worst, float(np.abs(y - want).max()))
        if k is None or k is WRONG:  # the original's chunk (its connection's noise), bit for bit
            np.testing.assert_array_equal(y, want)
    same = KeyedPolicy(bundle, KEY)
    same.reset(seed=1)  # the key's chunk under another connection's noise differs: the noise is per row
    assert not np.allclose(same.controller.action_chunk(frames[0]), got[0], atol=1e-4)
    print(f"SmolVLA sealed: worst {worst:.2e}")
    assert worst <= 1e-4, worst


@pytest.fixture(scope="module")
def diffusion_bundle(tmp_path_factory):
    d = tmp_path_factory.mktemp("serve-diffusion")
    diffusion_base(d)
    api.personalize_checkpoint(
        str(d / "diffusion"), [(d / "user", KeySource(KEY, "file"))], d / "bundle",
        PersonalizeConfig.of(**TINY), general=d / "general",
    )  # fmt: skip
    return d / "bundle"


def test_diffusion_answers_whole_chunks_with_its_history_per_connection(diffusion_bundle, start_bundle):
    """Diffusion keeps its observation history on the connection's own module: each infer adds its frame
    and answers the chunk LeRobot's select_action queues; the first is n_action_steps select_action calls
    from a new episode."""
    from prop_cli.serve.chunks import batchable

    bundle = load_bundle(diffusion_bundle)
    assert not batchable(bundle)
    frames = _frames(bundle, 2, seed=11)
    steps = KeyedPolicy(bundle, KEY).controller.chunk_steps
    assert steps is not None and steps > 1
    running = start_bundle(diffusion_bundle)
    keyed = client_policy.WebsocketClientPolicy(host="127.0.0.1", port=running.port,
                                                api_key=np.packbits(KEY).tobytes().hex())  # fmt: skip
    assert keyed.get_server_metadata()["action_horizon"] == steps
    first, second = keyed.infer(frames[0])["actions"], keyed.infer(frames[1])["actions"]
    policy = KeyedPolicy(bundle, KEY)
    policy.reset()
    want_first = np.stack([policy.select_action(frames[0]) for _ in range(steps)])
    np.testing.assert_allclose(first, want_first, rtol=0, atol=1e-5)
    policy.reset()  # the same two infers in process: the history holds frame 0 then frame 1
    policy.controller.action_chunk(frames[0])
    np.testing.assert_allclose(second, policy.controller.action_chunk(frames[1]), rtol=0, atol=1e-5)
    assert keyed.infer({"reset": True}) == {"reset": True}
    again = keyed.infer(frames[0])["actions"]  # a new episode: its first chunk again
    np.testing.assert_allclose(again, want_first, rtol=0, atol=1e-5)
    keyed._ws.close()


@pytest.fixture(scope="module")
def pi0_sealed(tmp_path_factory):
    """A tiny pi0 (examples/pi_tiny.py) sealed for a 32-bit key (LoRA payload); pi_tiny.tiny() stays on
    for the rest of the module (a tiny pi0 loads back only under it): this file's last test uses it."""
    from examples import pi_tiny

    with pi_tiny.tiny():
        d = tmp_path_factory.mktemp("serve-pi0")
        task.record(d / "general", 2, 0, np.zeros(3, np.float32), camera=True)
        task.record(d / "user", 2, 50_000, task.USER_OFFSET, camera=True)
        built = pi_tiny.build_pi("pi0", pi_tiny.build_tokenizer(d / "tok"), task.dataset_stats(d / "general"))
        task.train_base(d / "general", d / "pi0", steps=3, built=built)
        cfg = PersonalizeConfig.of(
            **(TINY | {"seal": True, "steps": 8, "payload": "lora", "payload_rank": 2})
        )
        api.personalize_checkpoint(
            str(d / "pi0"), [(d / "user", KeySource(KEY32, "file"))], d / "sealed", cfg
        )
        yield d / "sealed"


KEY32 = np.random.default_rng(4).integers(0, 2, 32).astype(np.uint8)


def test_pi0_rows_of_users_share_a_forward_each_with_its_own_noise(pi0_sealed):
    from prop_cli.serve.cache import BehaviourCache
    from prop_cli.serve.chunks import batchable
    from prop_cli.serve.sessions import Session, chunk_runner, payload_table

    bundle = load_bundle(pi0_sealed)
    assert batchable(bundle)
    runner, cache = chunk_runner(bundle, payload_table(bundle)), BehaviourCache(2**26)
    who = [KEY32, None, KEY32]
    sessions = [Session(bundle, k, True, cache, runner) for k in who]
    for i, s in enumerate(sessions):
        s.reset(seed=i)
    frames = [f | {"task": "reach the goal"} for f in _frames(bundle, len(who), seed=13)]
    before = runner.batches
    got = runner.run([s.chunk_request(f) for s, f in zip(sessions, frames)])
    assert runner.batches == before + 2  # the user's rows together, the no-key request alone
    worst = 0.0
    for i, (k, f, y) in enumerate(zip(who, frames, got)):
        policy = KeyedPolicy(bundle, k)
        policy.reset(seed=i)
        want = policy.controller.action_chunk(f)
        assert y.shape == want.shape == (runner.steps, want.shape[-1])
        worst = max(worst, float(np.abs(y - want).max()))
    print(f"pi0 sealed: worst {worst:.2e}")
    assert worst <= 1e-4, worst
