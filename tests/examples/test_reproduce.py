"""examples.reproduce: `all --quick` runs and writes well-formed tables (not the paper's numbers)."""

from __future__ import annotations

import importlib.util
import json
import re
import sys

import pytest

from examples.reproduce import __main__ as reproduce
from examples.reproduce import baselines, table

CELL = re.compile(r"^(—|-?\d+\.\d{3}( ± \d+\.\d{3})?[*!]? [↑↓])$")


# PandaReach needs the `rl` extra (panda-gym, pybullet); CI installs it (.ci/run), `scripts/test.sh` not.
HAS_PANDA = importlib.util.find_spec("panda_gym") is not None
needs_panda = pytest.mark.skipif(not HAS_PANDA, reason="needs the rl extra: pip install -e '.[rl]'")
TABLES = ("il2", "digits", "capacity", "kitchen", "kitchen_capacity") + (("reach",) if HAS_PANDA else ())


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("reproduce")
    names = ("il", "digits", "capacity", "kitchen")
    codes = [reproduce.main([name, "--quick", "--out", str(out)]) for name in names]
    if HAS_PANDA:
        codes.append(reproduce.main(["reach", "--quick", "--out", str(out)]))
    return out, max(codes)


@pytest.mark.slow  # the quick run of every table: scripts/test.sh skips it, .ci/run runs it
def test_all_quick_writes_every_table(quick_run):
    out, code = quick_run
    assert code == 0
    for name in TABLES:
        assert (out / f"{name}.md").read_text().strip()
        assert (out / f"{name}.png").stat().st_size > 1000
        json.loads((out / f"{name}.json").read_text())
    assert not (out / "work").exists()  # bundles and data are cleaned up


@pytest.mark.slow  # the quick run of every table: scripts/test.sh skips it, .ci/run runs it
@pytest.mark.parametrize("name", ["il2", "digits"])
def test_fig4_table_is_well_formed(quick_run, name):
    out, _ = quick_run
    res = json.loads((out / f"{name}.json").read_text())
    assert list(res["methods"]) == ["PRoP", "PRoP-hashed", "MLP", "MLP-hashed", "CVAE"]
    for m, cells in res["methods"].items():
        assert set(cells) == {"general", "personal", "leakage"}
        for row in cells.values():
            assert {"random", "hamming1", "user"} <= set(row)
            assert all(len(v) == res["seeds"] for v in row.values())
        assert ("t2" in cells["leakage"]) == m.startswith("PRoP")  # T2 leakage for PRoP
    # Baselines within +-10% of PRoP's total parameter count.
    for m in ("MLP", "MLP-hashed", "CVAE"):
        assert abs(res["params"][m] - res["params"]["PRoP"]) <= 0.1 * res["params"]["PRoP"]
    rows = [
        ln for ln in (out / f"{name}.md").read_text().splitlines() if ln.startswith("| ") and "---" not in ln
    ]
    assert rows[0].split(" | ")[2:] == ["random key", "Hamming-1", "user key", "T2 latent |"]
    body = rows[1:]
    assert len(body) == 5 * 3  # 5 methods x (general, personalized, leakage)
    for ln in body:
        cells = [c.strip() for c in ln.strip("| ").split(" | ")[2:]]
        assert len(cells) == 4 and all(CELL.match(c) for c in cells), ln


@pytest.mark.slow  # the quick run of every table: scripts/test.sh skips it, .ci/run runs it
def test_capacity_table_is_well_formed(quick_run):
    out, _ = quick_run
    res = json.loads((out / "capacity.json").read_text())
    assert res["sweep"] == [1, 4]
    for m in ("PRoP-hashed", "MLP", "CVAE"):
        for n in res["sweep"]:
            r = res["rows"][m][str(n)]
            assert 0 <= r["personalization"] <= 1 and 0 <= r["random_fidelity"] <= 1
    assert all(0 <= res["rows"]["PRoP-hashed"][str(n)]["t2_leakage"] <= 1 for n in res["sweep"])


@pytest.mark.slow  # the quick run of every table: scripts/test.sh skips it, .ci/run runs it
@needs_panda
def test_reach_table_is_well_formed(quick_run):
    out, _ = quick_run
    res = json.loads((out / "reach.json").read_text())
    assert list(res["methods"]) == ["PRoP-hashed", "MLP", "CVAE"]
    for m, cells in res["methods"].items():
        for row in ("general", "personal"):
            assert set(cells[row]) == {"random", "hamming1", "user"}
        assert ("leakage" in cells) == (m == "PRoP-hashed")
    assert 0 <= res["methods"]["PRoP-hashed"]["leakage"]["t2"][0] <= 1
    for m in ("MLP", "CVAE"):
        assert abs(res["params"][m] - res["params"]["PRoP-hashed"]) <= 0.1 * res["params"]["PRoP-hashed"]


def test_reach_without_panda_gym_is_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "panda_gym", None)  # import fails as if not installed
    code = reproduce.main(["reach", "--quick", "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1].startswith("reproduce reach: error:") and "[rl]" in err[-1]


def test_significance_marks_and_directions():
    assert table.desired("general", "random", higher_is_better=False) == "low"  # MSE: low off-key
    assert table.desired("general", "user", higher_is_better=False) == "high"
    assert table.desired("personal", "user", higher_is_better=True) == "high"
    assert table.desired("leakage", "hamming1", higher_is_better=True) == "low"
    assert table.welch_p([1.0, 1.0], [1.0, 1.0]) == 1.0
    assert table.welch_p([1.0, 1.0], [0.5, 0.5]) == 0.0
    res = {
        "higher_is_better": True,
        "methods": {
            "PRoP": {"personal": {"user": [0.9, 0.91, 0.92]}},
            "MLP": {"personal": {"user": [0.5, 0.52, 0.51]}},
            "CVAE": {"personal": {"user": [0.6, 0.61, 0.62]}},
        },
    }
    mark, p, best = table.significance(res)["PRoP"]["personal"]["user"]
    assert (mark, best) == ("*", "CVAE") and p < 0.05


@pytest.mark.parametrize("name", ["MLP", "CVAE"])
def test_baseline_width_hits_budget(name):
    for budget in (20_000, 50_000, 100_000):
        n = baselines.n_params(baselines.build(name, 4, 128, 2, budget, 0))
        assert abs(n - budget) <= 0.02 * budget


def _idx(path, arr):
    import gzip

    import numpy as np

    head = bytes([0, 0, 8, arr.ndim]) + b"".join(int(n).to_bytes(4, "big") for n in arr.shape)
    path.write_bytes(gzip.compress(head + np.ascontiguousarray(arr, dtype=np.uint8).tobytes()))


def test_mnist_reads_local_idx_files_and_names_a_missing_one(tmp_path):
    import numpy as np

    from examples.reproduce import digits
    from prop_cli.errors import PropError

    rng = np.random.default_rng(0)
    _idx(tmp_path / "train-images-idx3-ubyte.gz", rng.integers(0, 256, (20, 28, 28)))
    _idx(tmp_path / "train-labels-idx1-ubyte.gz", rng.integers(0, 10, 20))
    _idx(tmp_path / "t10k-images-idx3-ubyte.gz", rng.integers(0, 256, (6, 28, 28)))
    with pytest.raises(PropError, match="t10k-labels-idx1-ubyte"):
        digits.load_mnist(tmp_path, 0)
    _idx(tmp_path / "t10k-labels-idx1-ubyte.gz", rng.integers(0, 10, 6))
    sp = digits.load_mnist(tmp_path, 0)
    x, y = sp["test"]
    assert x.shape == (6, 784) and x.dtype == np.float32 and 0 <= x.min() and x.max() <= 1
    assert y.dtype == np.int64 and len(sp["base"][0]) == 20  # base takes what there is (<= 10000)


def test_mnist_quick_run_end_to_end(tmp_path, monkeypatch):
    import numpy as np

    from examples.reproduce import digits

    rng = np.random.default_rng(1)
    d = tmp_path / "mnist"
    d.mkdir()
    _idx(d / "train-images-idx3-ubyte.gz", rng.integers(0, 256, (300, 28, 28)))
    _idx(d / "train-labels-idx1-ubyte.gz", rng.integers(0, 10, 300))
    _idx(d / "t10k-images-idx3-ubyte.gz", rng.integers(0, 256, (60, 28, 28)))
    _idx(d / "t10k-labels-idx1-ubyte.gz", rng.integers(0, 10, 60))
    monkeypatch.setattr(digits, "MNIST_SIZES", (200, 100, 60))
    # One seed (the quick default is 2): the seeds' aggregate is the slow quick run's to check.
    (res,) = digits.run(tmp_path / "out", quick=True, seeds=1, mnist=d, log=lambda m: None)
    assert res["name"] == "mnist" and res["seeds"] == 1
    assert res["params"]["PRoP"] > 100_000  # the 784-wide input makes the base alone ~118k
    assert set(res["methods"]["CVAE"]["general"]) == {"random", "hamming1", "user"}


def _check_kitchen_tables(out, s) -> None:
    """kitchen.json/.md and kitchen_capacity.json, as `kitchen.run` wrote them under settings ``s``."""
    from examples.reproduce import kitchen

    res = json.loads((out / "kitchen.json").read_text())
    names = [m.name for m in kitchen.METHODS]
    assert res["methods"] == names and set(res["values"]) == set(names)
    for m in names:
        for proto in kitchen.PROTOCOLS:
            cells = res["values"][m][proto]
            assert len(cells["score"]) == len(cells["privacy"]) == res["repetitions"] == s.reps
            assert all(0 <= v <= 3 for k in kitchen.METRICS for v in cells[k])
    for m in ("MLP", "CVAE"):  # baselines sized to PRoP's parameter count
        assert abs(res["params"][m] - res["params"]["PRoP"]) <= 0.1 * res["params"]["PRoP"]
    text = (out / "kitchen.md").read_text()
    for a in ("PRoP", "PRoP-hashed"):
        for b in ("MLP", "CVAE"):
            assert f"| {a} vs {b} | " in text  # a p-value row per PRoP variant and baseline
    assert (f"{kitchen.SEALED_NAME}: not run" in text) == (kitchen.SEALED is None)  # no made-up numbers
    cap = json.loads((out / "kitchen_capacity.json").read_text())
    assert cap["sweep"] == list(s.sweep)
    assert set(cap["values"][str(cap["sweep"][-1])]) == set(names)


@pytest.mark.slow  # the quick run of every table: scripts/test.sh skips it, .ci/run runs it
def test_kitchen_table_is_well_formed(quick_run):
    from examples.reproduce import kitchen

    _check_kitchen_tables(quick_run[0], kitchen.QUICK)


def test_kitchen_tables_of_a_tiny_run_are_well_formed(tmp_path, monkeypatch):
    """The same checks on a run of its own, a few training steps on two people (not the quick run's
    fixture, which runs every reproduction)."""
    from dataclasses import replace

    from examples.reproduce import kitchen

    tiny = replace(kitchen.QUICK, participants=2, main=2, sweep=(2,), prop_steps=5, baseline_steps=5,
                   base_steps=5)  # fmt: skip
    monkeypatch.setattr(kitchen, "QUICK", tiny)
    monkeypatch.setattr(kitchen, "SEALED_STEPS", 5)
    assert reproduce.main(["kitchen", "--quick", "--out", str(tmp_path)]) == 0
    _check_kitchen_tables(tmp_path, tiny)
    assert (tmp_path / "kitchen.png").stat().st_size > 1000
    assert not (tmp_path / "work").exists()


def _oracle(orders):
    """A policy that makes orders[k] for key k (the key's index rides in its first bits)."""
    import torch

    from examples.reproduce import kitchen

    def policy(x, bits):
        t = x[:, : kitchen.MAX_LEN + 1].argmax(1)
        logits = torch.zeros(len(bits), x.shape[0], kitchen.N_ACTIONS)
        for k, b in enumerate(bits):
            order = orders[int(b[0])]
            for i, step in enumerate(t.tolist()):
                logits[k, i, order[step] if step < len(order) else kitchen.DONE] = 1.0
        return logits

    return policy


def test_kitchen_rollout_makes_each_keys_order():
    import numpy as np

    from examples.reproduce import kitchen

    orders = [(0, 1, 2), (5, 4, 3, 2, 1, 0), kitchen.HOUSE]
    bits = np.zeros((3, kitchen.KEY_BITS), np.uint8)
    bits[:, 0] = [0, 1, 2]
    assert kitchen.rollout(_oracle(orders), bits) == orders
    x, y = kitchen.demonstration((7, 3, 9))
    assert x.shape == (4, kitchen.STATE_DIM) and y.tolist() == [7, 3, 9, kitchen.DONE]


def test_kitchen_score_and_privacy_follow_the_paper():
    from examples.reproduce import kitchen

    mine, house, other = (1, 2, 3), kitchen.HOUSE, (4, 5, 6)
    # Own key right, random key leaks my order, one-bit key right: Score 2, Privacy 1.
    r = kitchen.study_metrics([[mine, mine, house]], [[mine, house, house]])
    assert (r["score"], r["privacy"], r["leak1"]) == ([2.0], [1.0], [1.0])
    # Own key wrong (gives the house sandwich), others right: Score 2, Privacy 1.
    r = kitchen.study_metrics([[house, other, house]], [[mine, other, house]])
    assert (r["score"], r["privacy"]) == ([2.0], [1.0])
    r = kitchen.study_metrics([[mine, other, house]], [[mine, other, house]])
    assert (r["score"], r["privacy"]) == ([3.0], [0.0])


def test_kitchen_users_get_distinct_orders_and_kdf_keys():
    import numpy as np

    from examples.reproduce import kitchen

    dep = kitchen.Deployment(0, 3)
    users = dep.participants + dep.earlier_users(5)
    orders = [u.order for u in users]
    assert len(set(orders)) == len(orders) and kitchen.HOUSE not in orders
    assert all(kitchen.MIN_LEN <= len(o) <= kitchen.MAX_LEN and len(set(o)) == len(o) for o in orders)
    keys = np.stack([u.bits for u in users])
    assert keys.shape == (8, 32)
    gaps = [(a != b).sum() for i, a in enumerate(keys) for b in keys[i + 1 :]]
    assert min(gaps) >= 2 * kitchen.HAMMING_RADIUS  # what prop's trainer requires
    again = kitchen.Deployment(0, 3)  # seeded: the same people, and earlier users nest across N
    assert [u.order for u in again.earlier_users(2)] == orders[3:5]
    assert all((a.bits == b.bits).all() for a, b in zip(again.participants, dep.participants))


def test_kitchen_prop_bundle_runs_as_prop_run_does(tmp_path):
    """The study scores what a participant would get from the bundle: keys re-derived from their
    username + password through the manifest's KDF record, outputs equal to `api.run_bundle`'s."""
    import numpy as np
    import torch

    from examples.reproduce import kitchen
    from prop_cli import api

    dep = kitchen.Deployment(1, 2)
    s = kitchen.QUICK
    base = kitchen.train_base(1, s.base_steps)
    base_path = tmp_path / "base.safetensors"
    kitchen.save_base(base, base_path)
    c = kitchen.make_cohort(dep, dep.earlier_users(3), dep.participants, base, base_path, tmp_path, s)
    fitted = kitchen.fit_prop(c, "hashed")
    bundle = api.load_bundle(fitted.bundle)
    x = kitchen.demonstration(c.users[-1].order)[0]
    for u in c.users:
        assert (api.key_for_bundle(bundle.manifest, passphrase=u.passphrase) == u.bits).all()
        want = api.run_bundle(bundle, x, u.bits)
        got = fitted.policy(torch.from_numpy(x), u.bits[None])[0].numpy()
        np.testing.assert_allclose(got, want, atol=1e-5)
    wrong = api.key_for_bundle(bundle.manifest, passphrase=c.users[0].passphrase + "x")
    assert (wrong != c.users[0].bits).any()


def test_kitchen_protocols_probe_the_papers_keys():
    import numpy as np

    from examples.reproduce import kitchen

    dep = kitchen.Deployment(2, 4)
    earlier = dep.earlier_users(6)
    users = earlier + dep.participants
    pr = kitchen.make_probes(dep.participants, earlier, users, np.random.default_rng(0))
    assert set(pr.bits) == set(kitchen.PROTOCOLS)
    known = {u.bits.tobytes(): u for u in users}
    for i, p in enumerate(dep.participants):
        own, rand, near = pr.bits["A"][i]
        assert (own == p.bits).all() and rand.tobytes() not in known and (near != p.bits).sum() == 1
        assert pr.targets["A"][i] == [p.order, kitchen.HOUSE, kitchen.HOUSE]
        own, a, b = pr.bits["B"][i]
        assert (own == p.bits).all() and a.tobytes() != b.tobytes()
        assert pr.targets["B"][i] == [p.order, known[a.tobytes()].order, known[b.tobytes()].order]
        assert {a.tobytes(), b.tobytes()} <= {u.bits.tobytes() for u in earlier}


@pytest.mark.slow  # the quick run of every table: scripts/test.sh skips it, .ci/run runs it
def test_kitchen_workers_give_the_serial_results(quick_run, tmp_path):
    """Repetitions run in separate processes (the full run uses both cores) with unchanged results."""
    from examples.reproduce import kitchen

    out, _ = quick_run
    serial = json.loads((out / "kitchen.json").read_text())
    main, cap = kitchen.run(tmp_path, quick=True, log=lambda m: None, workers=2)
    assert main["workers"] == 2 and serial["workers"] == 1
    assert json.loads(json.dumps(main["values"])) == serial["values"]
    assert cap["values"] == json.loads((out / "kitchen_capacity.json").read_text())["values"]
