"""Fixtures of the prop serve tests: a tiny MLP bundle (the CLI tests' personalize) and a server on a
free loopback port, stopped after each test."""

from __future__ import annotations

import pytest

pytest.importorskip("websockets")
pytest.importorskip("msgpack")

from prop_cli.bundle import load_bundle  # noqa: E402
from prop_cli.serve import PolicyServer, start_in_thread  # noqa: E402
from tests.serve.shares import personalize_here  # noqa: E402


@pytest.fixture(scope="module")
def served_bundle(tmp_path_factory):
    """A personalized tiny MLP bundle (k.bin enrolled, k2.bin not), made once for the module."""
    import numpy as np

    from tests.conftest import make_mlp_checkpoint, write_keys

    wd = tmp_path_factory.mktemp("serve")
    rng = np.random.default_rng(0)
    make_mlp_checkpoint(wd / "model.safetensors")
    x = rng.uniform(-1, 1, (200, 4)).astype(np.float32)
    np.savez(wd / "mine.npz", x=x, y=(-x[:, :2] * 0.5).astype(np.float32))
    write_keys(wd, ("k.bin", "k2.bin"), rng)
    personalize_here(wd)
    return wd


@pytest.fixture
def start_bundle():
    """start_bundle(path, **PolicyServer options) -> a running server on a free loopback port."""
    running = []

    def go(path, **options):
        server = PolicyServer(load_bundle(path), port=0, **options)
        running.append(start_in_thread(server))
        return running[-1]

    yield go
    for r in running:
        r.stop()


@pytest.fixture
def start(served_bundle, start_bundle):
    """start(**PolicyServer options) -> a running server on a free loopback port; all stopped at the end."""
    return lambda **options: start_bundle(served_bundle / "mine.prop", **options)
