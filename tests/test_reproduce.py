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
TABLES = ("il2", "digits", "capacity") + (("reach",) if HAS_PANDA else ())


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("reproduce")
    codes = [reproduce.main([name, "--quick", "--out", str(out)]) for name in ("il", "digits", "capacity")]
    if HAS_PANDA:
        codes.append(reproduce.main(["reach", "--quick", "--out", str(out)]))
    return out, max(codes)


def test_all_quick_writes_every_table(quick_run):
    out, code = quick_run
    assert code == 0
    for name in TABLES:
        assert (out / f"{name}.md").read_text().strip()
        assert (out / f"{name}.png").stat().st_size > 1000
        json.loads((out / f"{name}.json").read_text())
    assert not (out / "work").exists()  # bundles and data are cleaned up


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


def test_capacity_table_is_well_formed(quick_run):
    out, _ = quick_run
    res = json.loads((out / "capacity.json").read_text())
    assert res["sweep"] == [1, 4]
    for m in ("PRoP-hashed", "MLP", "CVAE"):
        for n in res["sweep"]:
            r = res["rows"][m][str(n)]
            assert 0 <= r["personalization"] <= 1 and 0 <= r["random_fidelity"] <= 1
    assert all(0 <= res["rows"]["PRoP-hashed"][str(n)]["t2_leakage"] <= 1 for n in res["sweep"])


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
    (res,) = digits.run(tmp_path / "out", quick=True, seeds=2, mnist=d, log=lambda m: None)
    assert res["name"] == "mnist" and res["seeds"] == 2
    assert res["params"]["PRoP"] > 100_000  # the 784-wide input makes the base alone ~118k
    assert set(res["methods"]["CVAE"]["general"]) == {"random", "hamming1", "user"}
