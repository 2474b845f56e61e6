"""prop serve-ray: the policy server as a Ray Serve application on a local Ray instance on the loopback,
openpi-client connecting unchanged; users routed by their routing id (Ray Serve's model multiplexing).

The Ray tests need the `ray` extra (``pip install 'prop-keys[ray]'``); without ray they are skipped with
the reason; they are slow (a local Ray instance and its Serve take ~25 s to start on 2 CPUs). The routing
id's own test needs only prop."""

from __future__ import annotations

import socket
import subprocess
import sys

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed

from prop_cli.bundle import load_bundle
from prop_cli.bundle.cipher import lookup_name
from prop_cli.core.key_files import key_text, read_key_file
from prop_cli.run import KeyedPolicy
from prop_cli.serve.route import NO_KEY, route_salt, routing_id
from tests.conftest import write_keys
from tests.serve.shares import OPENPI_CONNECT, personalize_here, routed_rounds, start_serve_ray

X = np.random.default_rng(7).uniform(-1, 1, (5, 4)).astype(np.float32)
ATOL = 1e-5  # a batched row against the folded weights: float rounding (docs/serving.md)


def test_a_routing_id_is_the_keys_own_and_says_nothing_of_it():
    rng = np.random.default_rng(3)
    a, b = (rng.integers(0, 2, 128).astype(np.uint8) for _ in range(2))
    one, two = bytes(range(16)), bytes(range(1, 17))
    rid = routing_id(a, one)
    assert rid == routing_id(a.copy(), one) and len(rid) == 32  # stable: the same user, the same replica
    assert rid != routing_id(b, one)  # users apart
    assert rid != routing_id(a, two)  # another bundle: an unrelated id (no linking users across bundles)
    key = np.packbits(a).tobytes()
    import hashlib

    plain = {key.hex(), hashlib.sha256(key).hexdigest(), hashlib.sha256(key).hexdigest()[:32]}
    assert rid not in plain and rid[:16] not in key.hex()  # never the key nor a plain hash of it
    assert rid != lookup_name(a, one.hex())  # nor the bundle's lookup name of its record
    assert routing_id(None, one) == NO_KEY
    assert route_salt({"bundle_id": one.hex()}) == one
    assert len(route_salt({"format": 4})) == 32  # no bundle id: the manifest's digest


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def two_users(served_bundle):
    """The tiny MLP sealed (LoRA) for k.bin, k2.bin added; k3.bin enrolled in nothing."""
    wd = served_bundle
    write_keys(wd, ("k3.bin",), np.random.default_rng(9))
    personalize_here(wd, "ray.prop", "--seal", "--payload", "lora", "--payload-rank", "2")
    x = np.load(wd / "mine.npz")["x"]
    np.savez(wd / "theirs.npz", x=x, y=(x[:, 2:] * 0.7).astype(np.float32))
    code = "from prop_cli.cli.main import main; main()"
    args = ["add-user", wd / "ray.prop", "--data", wd / "theirs.npz", "--key-file", wd / "k2.bin",
            "--steps", "40", "--device", "cpu"]  # fmt: skip
    done = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                          timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    return wd


@pytest.fixture(scope="module")
def needs_ray():
    """Skip (before any bundle is made) without ray and openpi-client."""
    pytest.importorskip("ray", reason="prop serve-ray needs ray (pip install 'prop-keys[ray]')")
    pytest.importorskip("openpi_client.websocket_client_policy")


@pytest.fixture(scope="module")
def ray_served(needs_ray, two_users):
    """The two-user bundle deployed on a local Ray instance on a free loopback port: 2 replicas, each
    holding at most 1 user, so a user served by a replica that already holds it shows routing at work."""
    import ray
    from ray import serve

    from prop_cli.serve.ray_app import APP_NAME, application

    port = _free_port()
    ray.init(address="local", include_dashboard=False, num_cpus=2, log_to_driver=False)
    try:
        serve.start(http_options={"host": "127.0.0.1", "port": port})
        app = application(two_users / "ray.prop", replicas=2, users_per_replica=1, replica_cpus=0.5)
        serve.run(app, name=APP_NAME, route_prefix="/")
        yield two_users, port
    finally:
        serve.shutdown()
        ray.shutdown()


def _client(port: int, key=None):
    from openpi_client.websocket_client_policy import WebsocketClientPolicy

    return WebsocketClientPolicy(host="127.0.0.1", port=port, api_key=key)


@pytest.mark.slow
@OPENPI_CONNECT
def test_two_users_and_no_key_through_ray_equal_their_own_runs(ray_served):
    wd, port = ray_served
    bundle = load_bundle(wd / "ray.prop")
    want = {
        name: KeyedPolicy(bundle, read_key_file(wd / name) if name else None).predict(X)[0]
        for name in (None, "k.bin", "k2.bin")
    }
    assert not np.allclose(want["k.bin"], want[None], atol=1e-3)
    assert not np.allclose(want["k2.bin"], want["k.bin"], atol=1e-3)
    clients = {name: _client(port, key_text(wd / name) if name else None) for name in want}
    for name, client in clients.items():
        meta = client.get_server_metadata()
        assert meta["keyed"] is (name is not None) and meta["input_shape"] == [4]
    for _ in range(2):  # interleaved: each user's own behaviour every time
        for name, client in clients.items():
            got = client.infer({"observation": X})["actions"]
            np.testing.assert_allclose(got, want[name], rtol=0, atol=ATOL)
    one = clients["k.bin"].infer({"observation": X[0]})["actions"]
    np.testing.assert_allclose(one, want["k.bin"][0], rtol=0, atol=ATOL)
    for client in clients.values():
        client._ws.close()


@pytest.mark.slow
@OPENPI_CONNECT
def test_a_wrong_key_is_refused_in_one_line_and_others_are_served(ray_served):
    wd, port = ray_served
    with pytest.raises(ConnectionClosed) as e:
        _client(port, key_text(wd / "k3.bin"))
    assert e.value.rcvd.code == 1008 and e.value.rcvd.reason.startswith("refused:"), e.value.rcvd
    assert "enrolled in nothing" in e.value.rcvd.reason and str(wd) not in e.value.rcvd.reason
    assert key_text(wd / "k3.bin") not in e.value.rcvd.reason
    ok = _client(port, key_text(wd / "k.bin"))
    assert ok.get_server_metadata()["keyed"] is True
    ok._ws.close()


@pytest.mark.slow
@OPENPI_CONNECT
def test_the_same_user_lands_on_the_replica_that_holds_it(ray_served):
    wd, port = ray_served
    users = ("k.bin", "k2.bin")
    keys = {n: key_text(wd / n) for n in users}
    rounds = routed_rounds(lambda key: _client(port, key), keys, {"observation": X})
    for name in users:
        assert {r[name] for r in rounds} == {(rounds[0][name][0], True)}, (name, rounds)
    # One user a replica (each holds one at most): a random pick would miss half the time.
    assert rounds[0]["k.bin"][0] != rounds[0]["k2.bin"][0]


@pytest.mark.slow
@OPENPI_CONNECT
def test_a_bundle_changed_on_disk_refuses_new_connections(ray_served):
    """Runs after the tests above on the module's deployment: it leaves that bundle refused."""
    import os

    wd, port = ray_served
    manifest = wd / "ray.prop" / "manifest.json"
    st = manifest.stat()
    os.utime(manifest, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    for name in ("k.bin", None):  # a held user too: as prop serve, no new connection after a change
        with pytest.raises(ConnectionClosed) as e:
            _client(port, key_text(wd / name) if name else None)
        assert e.value.rcvd.code == 1008 and "changed on disk" in e.value.rcvd.reason


def test_serve_ray_off_the_loopback_without_tls_is_one_line_before_ray_starts(cli, tmp_path):
    r = cli("serve-ray", tmp_path / "any.prop", "--host", "0.0.0.0")  # checked before the bundle is read
    assert r.code == 2 and "Traceback" not in r.err
    assert r.err.startswith("prop: error: --host 0.0.0.0 is not the loopback") and r.err.count("\n") == 1


def test_serve_ray_without_ray_names_the_extra(cli, tmp_path):
    try:
        import ray.serve  # noqa: F401
    except ImportError:
        r = cli("serve-ray", tmp_path / "any.prop")
        assert r.code == 2 and r.err.count("\n") == 1 and "pip install 'prop-keys[ray]'" in r.err, r.err
    else:
        pytest.skip("ray is installed here: the missing-extra message cannot show")


@pytest.mark.slow
@OPENPI_CONNECT
def test_prop_serve_ray_serves_until_sigterm(needs_ray, two_users):
    """The CLI end to end: its URL on stdout, openpi-client through it, SIGTERM stops it cleanly."""
    import json
    import signal

    wd, port = two_users, _free_port()
    proc, line = start_serve_ray(wd / "ray.prop", port)
    try:
        assert json.loads(line)["url"] == f"ws://127.0.0.1:{port}", (line, proc.stderr.read())
        client = _client(port, key_text(wd / "k.bin"))
        want = KeyedPolicy(load_bundle(wd / "ray.prop"), read_key_file(wd / "k.bin")).predict(X)[0]
        np.testing.assert_allclose(client.infer({"observation": X})["actions"], want, rtol=0, atol=ATOL)
        client._ws.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "stopped" in err and "Traceback" not in err, err
    assert key_text(wd / "k.bin") not in err
