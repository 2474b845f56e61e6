"""prop run (prop_cli/cli/run_cmd.py): a damaged or newer bundle, a key of the wrong size or enrolled in
nothing, an input of the wrong shape."""

from __future__ import annotations

import json

import numpy as np

from prop_cli import constants as C
from tests.cli.shares import assert_clean_error


def test_tampered_bundle(cli, workdir, bundle):
    f = bundle / C.BASE_WEIGHTS
    blob = bytearray(f.read_bytes())
    blob[-1] ^= 1
    f.write_bytes(bytes(blob))
    res = cli("run", bundle, "--input", workdir / "x.npy", "--output", workdir / "y.npy")
    assert_clean_error(res, C.BASE_WEIGHTS, "sha256")
    assert not (workdir / "y.npy").exists()


def test_newer_format_version(cli, workdir, bundle):
    m = json.loads((bundle / C.MANIFEST).read_text())
    m[C.M_FORMAT] = C.FORMAT_VERSION + 1
    (bundle / C.MANIFEST).write_text(json.dumps(m))
    res = cli("run", bundle, "--input", workdir / "x.npy", "--output", workdir / "y.npy")
    assert_clean_error(res, "format version", "upgrade")


def test_wrong_key_size_for_bundle(cli, workdir, bundle):
    (workdir / "short.bin").write_bytes(b"\x01" * 8)
    res = cli(
        "run",
        bundle,
        "--input",
        workdir / "x.npy",
        "--key-file",
        workdir / "short.bin",
        "--output",
        workdir / "y.npy",
    )
    assert_clean_error(res, "short.bin", "128")


def test_a_key_enrolled_in_nothing_fails_unless_allowed(cli, workdir, bundle):
    """Issue 31: `prop run` with a key that opens nothing exited 0 with one warning line (and the base's
    outputs); now it is exit 2, one line, nothing written, unless --allow-unenrolled-key, which every
    command that runs a key offers."""
    from prop_cli.cli.main import app

    (workdir / "other.bin").write_bytes(bytes(range(16)))
    (workdir / "other.bin").chmod(0o600)
    args = ["run", bundle, "--input", workdir / "x.npy", "--key-file", workdir / "other.bin", "--json"]
    res = cli(*args, "--output", workdir / "y.npy")
    assert_clean_error(res, f"the key is enrolled in nothing in {bundle}", "--allow-unenrolled-key")
    assert not res.out and not (workdir / "y.npy").exists()
    res = cli(*args, "--output", workdir / "y.npy", "--allow-unenrolled-key")
    assert res.code == 0 and json.loads(res.out)["keyed"] is False, res.err
    assert "prop: warning: the key is enrolled in nothing" in res.err
    assert cli("run", bundle, "--input", workdir / "x.npy", "--output", workdir / "y0.npy").code == 0
    np.testing.assert_array_equal(np.load(workdir / "y.npy"), np.load(workdir / "y0.npy"))
    takes = {c.name for c in app.registered_commands if "--allow-unenrolled-key" in cli(c.name, "--help").out}
    assert takes == {"run", "eval", "export", "attack", "serve", "serve-ray"}


def test_wrong_input_shape_for_run(cli, workdir, bundle):
    np.save(workdir / "x5.npy", np.zeros((3, 5), np.float32))
    res = cli("run", bundle, "--input", workdir / "x5.npy", "--output", workdir / "y.npy")
    assert_clean_error(res, "x5.npy", "(4,)")
