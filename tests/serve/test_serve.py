"""prop serve: openpi-client's WebsocketClientPolicy, unchanged, against a server on the loopback."""

from __future__ import annotations

import base64
import logging

import msgpack
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from prop_cli.bundle import load_bundle
from prop_cli.core.key_files import key_from_text, key_text, read_key_file
from prop_cli.errors import PropError
from prop_cli.run import KeyedPolicy
from prop_cli.serve import packb, unpackb
from tests.serve.shares import OPENPI_CONNECT

client_policy = pytest.importorskip("openpi_client.websocket_client_policy")
pytestmark = OPENPI_CONNECT
Client = client_policy.WebsocketClientPolicy

X = np.random.default_rng(1).uniform(-1, 1, (5, 4)).astype(np.float32)
TIMEOUT = 20  # seconds any one receive may wait: a test never hangs


def expected(bundle_dir, key_name=None) -> np.ndarray:
    bundle = load_bundle(bundle_dir / "mine.prop")
    key = read_key_file(bundle_dir / key_name) if key_name else None
    return KeyedPolicy(bundle, key).predict(X)[0]


def raw(running, key: str | None = None):
    """A plain websockets connection (for what openpi-client never sends), its metadata read."""
    headers = {"Authorization": f"Api-Key {key}"} if key else None
    ws = connect(running.url, additional_headers=headers, open_timeout=TIMEOUT, max_size=None)  # noqa: SIM115
    meta = unpackb(ws.recv(timeout=TIMEOUT))
    return ws, meta


def test_key_text_round_trips(served_bundle):
    text = key_text(served_bundle / "k.bin")
    assert text == (served_bundle / "k.bin").read_bytes().hex()
    assert np.array_equal(key_from_text(text, 128), read_key_file(served_bundle / "k.bin"))
    with pytest.raises(PropError, match="hex") as e:
        key_from_text("zz" * 16, 128)
    assert "zz" not in str(e.value)  # a refusal never quotes the key text
    with pytest.raises(PropError, match="32 hex"):
        key_from_text("ab", 128)


def test_openpi_client_no_key_user_key_and_two_users_at_once(start, served_bundle):
    running = start()
    base, user = expected(served_bundle), expected(served_bundle, "k.bin")
    assert not np.allclose(base, user)  # the key changes the behaviour, so the comparisons below can fail
    nokey = Client(host="127.0.0.1", port=running.port)
    keyed = Client(host="127.0.0.1", port=running.port, api_key=key_text(served_bundle / "k.bin"))
    assert nokey.get_server_metadata()["keyed"] is False
    assert keyed.get_server_metadata()["keyed"] is True
    assert keyed.get_server_metadata()["observation"] == "observation"
    for _ in range(2):  # interleaved: each connection keeps its own policy
        np.testing.assert_array_equal(nokey.infer({"observation": X})["actions"], base)
        np.testing.assert_allclose(keyed.infer({"observation": X})["actions"], user, rtol=0, atol=1e-6)
    one = keyed.infer({"observation": X[0]})["actions"]  # one observation, no batch axis
    assert one.shape == user[0].shape
    for c in (nokey, keyed):
        c._ws.close()


def test_a_key_enrolled_in_nothing_is_refused_with_a_reason(start, served_bundle):
    running = start()
    with pytest.raises(ConnectionClosed) as e:
        Client(host="127.0.0.1", port=running.port, api_key=key_text(served_bundle / "k2.bin"))
    assert e.value.rcvd.code == 1008 and e.value.rcvd.reason.startswith("refused:")
    assert str(served_bundle) not in e.value.rcvd.reason  # the server's paths stay on the server
    with pytest.raises(ConnectionClosed) as e:
        raw(running, "not-hex-" * 4)
    assert e.value.rcvd.code == 1008
    # The server goes on serving everyone else.
    ok = Client(host="127.0.0.1", port=running.port, api_key=key_text(served_bundle / "k.bin"))
    assert ok.get_server_metadata()["keyed"] is True
    ok._ws.close()


def test_allow_unenrolled_key_runs_the_base(start, served_bundle):
    running = start(allow_unenrolled=True)
    c = Client(host="127.0.0.1", port=running.port, api_key=key_text(served_bundle / "k2.bin"))
    assert c.get_server_metadata()["keyed"] is False
    np.testing.assert_array_equal(c.infer({"observation": X})["actions"], expected(served_bundle))
    c._ws.close()


def _packed_array(dtype: str, shape, data: bytes) -> bytes:
    return msgpack.packb({"observation": {b"__ndarray__": True, b"data": data, b"dtype": dtype,
                                          b"shape": shape}})  # fmt: skip


@pytest.mark.parametrize(
    "message, words",
    [
        ("hello", "not text"),
        (b"\xc1\xff\x00garbage", "not a msgpack"),
        (packb([1, 2, 3]), "is a dict"),
        (packb({"obs": X}), "'observation'"),
        (packb({"observation": X[:, :3]}), "shape"),
        (_packed_array("|O", [2], b"\0" * 16), "refused"),
        (_packed_array("|V8", [2], b"\0" * 16), "refused"),
        (_packed_array("<f4", [5, 4], b"\0" * 12), "bytes"),  # truncated data
        (packb({"observation": "text"}), "numeric array"),
    ],
)
def test_bad_input_gets_one_line_and_the_connection_goes_on(start, served_bundle, message, words):
    running = start()
    ws, _ = raw(running)
    ws.send(message)
    reply = ws.recv(timeout=TIMEOUT)
    assert isinstance(reply, str) and reply.startswith("prop serve: error:") and words in reply, reply
    assert "\n" not in reply and "Traceback" not in reply
    ws.send(packb({"observation": X}))  # the same connection still answers
    np.testing.assert_array_equal(unpackb(ws.recv(timeout=TIMEOUT))["actions"], expected(served_bundle))
    ws.close()


def test_an_oversize_message_closes_that_connection_only(start, served_bundle):
    running = start(max_message_bytes=4096)
    ws, _ = raw(running)
    ws.send(packb({"observation": np.zeros((1000, 4), np.float32)}))
    with pytest.raises(ConnectionClosed) as e:
        ws.recv(timeout=TIMEOUT)
    assert e.value.rcvd.code == 1009
    other, meta = raw(running)
    other.send(packb({"observation": X}))
    assert unpackb(other.recv(timeout=TIMEOUT))["actions"].shape == expected(served_bundle).shape
    other.close()


def test_max_connections(start):
    running = start(max_connections=1)
    first, _ = raw(running)
    with pytest.raises(ConnectionClosed) as e:
        raw(running)
    assert e.value.rcvd.code == 1013
    first.close()


def test_the_key_is_never_logged_or_echoed(start, served_bundle, caplog, capsys):
    caplog.set_level(logging.DEBUG)  # every logger, websockets' own included, at its most verbose
    running = start()
    key_bytes = (served_bundle / "k.bin").read_bytes()
    text = key_text(served_bundle / "k.bin")
    forms = {text, text.upper(), base64.b64encode(key_bytes).decode(), key_bytes.decode("latin-1")}
    c = Client(host="127.0.0.1", port=running.port, api_key=text)
    c.infer({"observation": X})
    meta = packb(c.get_server_metadata())
    c._ws.close()
    with pytest.raises(ConnectionClosed) as e:  # a refused key's close reason does not echo it
        Client(host="127.0.0.1", port=running.port, api_key=key_text(served_bundle / "k2.bin"))
    reason = e.value.rcvd.reason
    running.stop()
    cap = capsys.readouterr()
    # The client's own websockets logger prints the header it sends at DEBUG (docs/deploy.md warns of it):
    # that is the client's process; every record of the server's side is checked.
    logged = "\n".join(r.getMessage() for r in caplog.records if not r.name.startswith("websockets.client"))
    assert "connected (keyed)" in logged  # the log was captured, so its absence below means something
    wrong = key_text(served_bundle / "k2.bin")
    for form in forms | {wrong}:
        for where, s in (("log", logged), ("stdout", cap.out), ("stderr", cap.err), ("reason", reason)):
            assert form not in s, where
    assert key_bytes not in meta and text.encode() not in meta


def test_the_server_code_never_unpickles():
    """No pickle, np.load or allow_pickle on the serving path; the decoder refuses object arrays."""
    from pathlib import Path

    import prop_cli.serve as serve

    for path in Path(serve.__file__).parent.glob("*.py"):
        source = path.read_text()
        for word in ("import pickle", "pickle.load", "allow_pickle", "np.load", "torch.load", "dill"):
            assert word not in source, (path.name, word)
    with pytest.raises(ValueError, match="refused"):
        unpackb(_packed_array("|O", [1], b"\0" * 8))
    with pytest.raises(ValueError, match="cannot send"):
        packb({"a": np.array([object()])})


def test_tls_serves_wss(start, served_bundle, tmp_path):
    """--tls-cert/--tls-key: wss, and a client that trusts the certificate gets the same answers."""
    import datetime
    import ssl

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "localhost")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (
        x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
        .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=1))
        .not_valid_after(now + datetime.timedelta(hours=1))
        .add_extension(x509.SubjectAlternativeName([x509.DNSName("localhost")]), critical=False)
        .sign(key, hashes.SHA256())
    )  # fmt: skip
    (tmp_path / "c.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (tmp_path / "k.pem").write_bytes(key.private_bytes(serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8, serialization.NoEncryption()))  # fmt: skip
    running = start(host="localhost", tls_cert=tmp_path / "c.pem", tls_key=tmp_path / "k.pem")
    assert running.url.startswith("wss://localhost:")
    context = ssl.create_default_context(cafile=str(tmp_path / "c.pem"))
    headers = {"Authorization": f"Api-Key {key_text(served_bundle / 'k.bin')}"}
    with connect(running.url, ssl=context, additional_headers=headers, open_timeout=TIMEOUT) as ws:
        assert unpackb(ws.recv(timeout=TIMEOUT))["keyed"] is True
        ws.send(packb({"observation": X}))
        got = unpackb(ws.recv(timeout=TIMEOUT))["actions"]
    np.testing.assert_allclose(got, expected(served_bundle, "k.bin"), rtol=0, atol=1e-6)
