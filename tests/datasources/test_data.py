"""Data sources (reading) and data against the model (features, task, targets, bounds, split)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from prop_adapters import LoadedModel
from prop_cli.datasources import Dataset, load_data
from prop_cli.errors import PropError
from prop_cli.fit import check_features, prepare, resolve_task, split

load_npz = load_data  # the .npz source, through the registry


def _model(n_in=4, n_out=3, continuous=None, low=None, high=None) -> LoadedModel:
    torch.manual_seed(0)
    return LoadedModel(
        module=nn.Linear(n_in, n_out), spec={"adapter": "mlp"}, dtypes={}, input_shape=(n_in,), source="m",
        continuous=continuous, action_low=low, action_high=high,
    )  # fmt: skip


def _npz(tmp_path, name="d.npz", **arrays):
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


def _xy(n=20, d=4, labels=True):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(n, d))
    y = rng.integers(0, 3, size=n) if labels else rng.normal(size=(n, 2))
    return x, y


def test_classification_load(tmp_path):
    x, y = _xy()
    ds = load_npz(_npz(tmp_path, x=x, y=y.astype(np.int32)))
    assert ds.x.dtype == np.float32 and ds.x.shape == (20, 4)
    assert ds.y.dtype == np.int64
    assert len(ds) == 20 and ds.path.endswith("d.npz")
    assert prepare(_model(), ds)[1] == "classification"  # integer labels (N,), several outputs


def test_regression_load_and_bool_labels(tmp_path):
    x, y = _xy(labels=False)
    ds = load_npz(_npz(tmp_path, x=x, y=y))
    assert ds.y.dtype == np.float32 and prepare(_model(n_out=2), ds)[1] == "regression"
    ds = load_npz(_npz(tmp_path, "b.npz", x=x, y=y[:, 0] > 0))
    assert ds.y.dtype == np.int64 and prepare(_model(n_out=2), ds)[1] == "classification"


def test_no_y_optional(tmp_path):
    x, _ = _xy()
    ds = load_npz(_npz(tmp_path, x=x), require_y=False)
    assert ds.y is None and prepare(_model(), ds)[1] is None


def test_missing_file(tmp_path):
    with pytest.raises(PropError, match=r"nothere\.npz does not exist"):
        load_npz(tmp_path / "nothere.npz")


def test_not_an_npz(tmp_path):
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 definitely not a zip")
    with pytest.raises(PropError, match=r"junk\.npz is not a valid \.npz.*savez"):
        load_npz(tmp_path / "junk.npz")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(PropError, match=r"text\.npz is not a valid \.npz"):
        load_npz(tmp_path / "text.npz")
    np.save(tmp_path / "arr.npy", np.zeros((3, 2)))
    with pytest.raises(PropError, match=r"arr\.npy holds a single array"):
        load_npz(tmp_path / "arr.npy")


def test_no_x_lists_fields(tmp_path):
    x, y = _xy()
    with pytest.raises(PropError, match=r"d\.npz has no field 'x' \(fields: inputs, y\)"):
        load_npz(_npz(tmp_path, inputs=x, y=y))


def test_no_y_when_required(tmp_path):
    x, _ = _xy()
    with pytest.raises(PropError, match=r"d\.npz has no field 'y' \(fields: x\)"):
        load_npz(_npz(tmp_path, x=x))


def test_x_not_numeric(tmp_path):
    _, y = _xy()
    with pytest.raises(PropError, match=r"d\.npz: field 'x' has dtype <U"):
        load_npz(_npz(tmp_path, x=np.array([["a"]] * 20), y=y))
    with pytest.raises(PropError, match=r"o\.npz: field 'x' is an object array"):
        load_npz(_npz(tmp_path, "o.npz", x=np.array([{}, 1], dtype=object), y=y))


def test_x_must_be_2d(tmp_path):
    with pytest.raises(PropError, match=r"d\.npz: field 'x' has shape \(20,\).*reshape"):
        load_npz(_npz(tmp_path, x=np.zeros(20), y=np.zeros(20, dtype=int)))


def test_length_mismatch(tmp_path):
    x, y = _xy()
    with pytest.raises(PropError, match=r"d\.npz: field 'x' has 20 rows but field 'y' has 19 rows"):
        load_npz(_npz(tmp_path, x=x, y=y[:19]))


def test_nan_inf_rows(tmp_path):
    x, y = _xy()
    x[3, 1] = np.nan
    x[5, 0] = np.inf
    x[5, 2] = np.nan
    with pytest.raises(PropError, match=r"d\.npz: field 'x' has NaN or inf in 2 rows"):
        load_npz(_npz(tmp_path, x=x, y=y))
    x, yr = _xy(labels=False)
    yr[0, 0] = -np.inf
    with pytest.raises(PropError, match=r"r\.npz: field 'y' has NaN or inf in 1 row"):
        load_npz(_npz(tmp_path, "r.npz", x=x, y=yr))


def test_too_few_samples(tmp_path):
    x, y = _xy(n=5)
    with pytest.raises(PropError, match=r"d\.npz: field 'x' has 5 rows, fewer than the 10"):
        load_npz(_npz(tmp_path, x=x, y=y))
    assert len(load_npz(tmp_path / "d.npz", min_samples=5)) == 5


def test_y_ndim(tmp_path):
    x, _ = _xy()
    with pytest.raises(PropError, match=r"d\.npz: field 'y' has shape \(20, 2, 2\); it must be \(N,\)"):
        load_npz(_npz(tmp_path, x=x, y=np.zeros((20, 2, 2))))


def test_class_labels_must_be_1d(tmp_path):
    x, y = _xy()
    ds = load_npz(_npz(tmp_path, x=x, y=y[:, None]))
    assert prepare(_model(n_out=1), ds)[1] == "regression"  # integer (N, 1) targets: regression
    with pytest.raises(PropError, match=r"d\.npz: field 'y' \(class labels\) has shape \(20, 1\)"):
        prepare(_model(continuous=False), ds)


def test_negative_labels(tmp_path):
    x, y = _xy()
    y[:2] = -1
    with pytest.raises(PropError, match=r"d\.npz: field 'y' has 2 negative class labels"):
        prepare(_model(), load_npz(_npz(tmp_path, x=x, y=y)))


# ---- the task is decided against the model (issue 10, fix 2) -----------------------------------


def test_integer_y_for_a_continuous_model_is_regression(tmp_path):
    x, _ = _xy()
    box = _model(n_out=1, continuous=True, low=(-2.0,), high=(2.0,))
    zeros = load_npz(_npz(tmp_path, x=x, y=np.zeros(20, int)))
    ds, task = prepare(box, zeros)
    assert task == "regression" and ds.y.dtype == np.float32  # not "accuracy 1.0 after learning nothing"
    torques = load_npz(_npz(tmp_path, "t.npz", x=x, y=np.round(np.linspace(-2, 2, 20)).astype(int)))
    assert prepare(box, torques)[1] == "regression"  # negative integers are torques, not bad labels


def test_discrete_model_takes_integral_floats_as_labels(tmp_path):
    x, y = _xy()
    ds, task = prepare(_model(continuous=False), load_npz(_npz(tmp_path, x=x, y=y.astype(np.float64))))
    assert task == "classification" and ds.y.dtype == np.int64 and np.array_equal(ds.y, y)
    with pytest.raises(PropError, match="non-integer values"):
        prepare(_model(continuous=False), load_npz(_npz(tmp_path, "f.npz", x=x, y=y + 0.5)))


def test_unknown_model_and_the_task_override(tmp_path):
    x, y = _xy()
    assert resolve_task(y, _model(n_out=1), 1) == "regression"  # one output: not a classifier
    assert resolve_task(y, _model(), 3) == "classification"
    assert resolve_task(y, _model(), 3, override="regression") == "regression"
    labels = load_npz(_npz(tmp_path, x=x, y=y.astype(np.float32)))
    with pytest.raises(PropError, match="3 outputs"):
        prepare(_model(), labels)  # float y is regression, and then has the wrong width
    assert prepare(_model(), labels, task="classification")[1] == "classification"


def test_targets_outside_the_action_bounds_are_refused(tmp_path):
    """Issue 10, fix 6: the checkpoint records the bounds; targets beyond them are a units mistake."""
    x, _ = _xy()
    box = _model(n_out=2, continuous=True, low=(-1.0, -2.0), high=(1.0, 2.0))
    ok = np.tile([[1.0, -2.0]], (20, 1))
    prepare(box, load_npz(_npz(tmp_path, x=x, y=ok)))  # the bounds themselves are fine
    bad = ok.copy()
    bad[5, 1] = 2.5
    with pytest.raises(
        PropError, match=r"field 'y' has 1 value outside the action bounds .*row 5, output 1: 2\.5"
    ):
        prepare(box, load_npz(_npz(tmp_path, "b.npz", x=x, y=bad)))


def test_check_features(tmp_path):
    x, y = _xy()
    ds = load_npz(_npz(tmp_path, x=x, y=y))
    check_features(ds, (4,), "m.safetensors")
    check_features(ds, None, "m.safetensors")
    with pytest.raises(
        PropError, match=r"--data .*d\.npz: x has 4 features per sample but the model .* expects 6"
    ):
        check_features(ds, (6,), "m.safetensors")
    with pytest.raises(PropError, match=r"--general-data .*per-sample shape \(4,\)"):
        check_features(ds, (1, 2, 2), "cnn", flag="--general-data")


def test_check_targets(tmp_path):
    x, y = _xy()
    ds = load_npz(_npz(tmp_path, x=x, y=y))
    prepare(_model(), ds)
    with pytest.raises(PropError, match=r"d\.npz: field .y. has class label 2 .* only 2"):
        prepare(_model(n_out=2), ds)
    x, yr = _xy(labels=False)
    reg = load_npz(_npz(tmp_path, "r.npz", x=x, y=yr))
    prepare(_model(n_out=2), reg)
    with pytest.raises(PropError, match=r"r\.npz: field 'y' has 2 target values .* 3 outputs"):
        prepare(_model(n_out=3, continuous=True), reg)
    one = Dataset(x=reg.x.astype(np.float32), y=reg.y[:, 0], path="one.npz")
    prepare(_model(n_out=1), one)
    with pytest.raises(PropError, match=r"one\.npz: field 'y' has 1 target values"):
        prepare(_model(n_out=2), one)


def test_split_deterministic():
    x = np.arange(40, dtype=np.float32).reshape(20, 2)
    ds = Dataset(x=x, y=np.arange(20), path="s.npz")
    tr, va = split(ds, 0.25, seed=3)
    assert len(tr) == 15 and len(va) == 5
    assert sorted(np.concatenate([tr.y, va.y]).tolist()) == list(range(20))
    assert np.array_equal(tr.x[:, 0] / 2, tr.y)  # rows stay paired
    tr2, va2 = split(ds, 0.25, seed=3)
    assert np.array_equal(va.y, va2.y)
    assert not np.array_equal(va.y, split(ds, 0.25, seed=4)[1].y)
    assert len(split(ds, 0.001, seed=0)[1]) == 1
    assert len(split(ds, 0.0, seed=0)[1]) == 0
    with pytest.raises(PropError, match="--val-fraction 1.5"):
        split(ds, 1.5, seed=0)
