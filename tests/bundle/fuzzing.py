"""Seeded fuzzing of everything prop reads: bundles, checkpoints, .npz data and SB3 zips.

Each case takes a valid input (a seed: an unsealed and a sealed bundle, a safetensors and a torch
checkpoint, an .npz, an SB3 zip), applies one mutation drawn from a seeded generator, loads
the result the way prop does and sorts the outcome:

- ``error``: a ``PropError`` (what every damaged input must give);
- ``same``: it loaded, and everything that matters is identical to the original's (tensors, arrays,
  the model's outputs with and without the key, the manifest): the mutation hit bytes no one reads,
  such as a zip timestamp;
- ``changed``: it loaded, and something differs. Allowed only where the format itself cannot tell
  (a flipped bit in a safetensors tensor: that format has no checksum) and for ``edit`` mutations,
  which write a new well-formed file (for bundles: a field edited and the digest recomputed, as a
  hostile editor would);
- ``crash:<Type>``: any other exception. Never allowed;
- ``noop``: the mutation left every byte as it was (zeros over zeros); not loaded.

Used by tests/test_fuzz.py (a couple of thousand cases) and benchmarks/fuzz.py (10,000 per kind).
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import warnings
import zipfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file

import prop_adapters as adapters
from prop_cli import constants as C
from prop_cli.bundle import manifest as schema
from prop_cli.datasources import load_data
from prop_cli.errors import PropError
from prop_cli.files import dump_json

KINDS = ("bundle", "checkpoint", "npz", "sb3")
# Corruption: what a flaky disk or a cut-off download does. Each must end in `error` or `same`
# (or `changed` where the format has no checksum).
CORRUPTIONS = ("bitflip", "byte", "truncate", "zero", "append", "delete")
EDIT = "edit"  # a well-formed but different file (fields, arrays or entries edited)
MUTATIONS = (*CORRUPTIONS, EDIT)
# Values an edit puts in place of a JSON value: wrong types, edges, junk.
_ODD = [None, True, False, 0, -1, 1, 7, 2**31, 2**64, -(2**63), 0.5, -1e308, 1e308, "", "x", "relu",
        "../../etc/passwd", "0" * 64, [], [1], [None], {}, {"a": 1}, [[[]]], "NaN"]  # fmt: skip


@dataclass
class Seed:
    """A valid input: its files (relative path -> bytes), the entry point and how to fingerprint it."""

    kind: str
    name: str  # the path passed to the loader, relative to the case folder
    files: dict[str, bytes]
    load: Callable[[Path], object]  # path -> fingerprint (a comparable value); raises on failure
    checksummed: bool  # True: the format detects any flipped bit itself (no `changed` allowed)
    reference: object = None


# ---- fingerprints -------------------------------------------------------------------------------


def _tensors_digest(tensors: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for k in sorted(tensors):
        t = tensors[k].detach().cpu().contiguous()
        h.update(k.encode() + str(t.dtype).encode() + str(tuple(t.shape)).encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def _loaded_fingerprint(loaded: adapters.LoadedModel) -> tuple:
    state = {**loaded.module.state_dict(), **{f"extra:{k}": v for k, v in loaded.extra.items()}}
    return (json.dumps(loaded.spec, sort_keys=True), _tensors_digest(state), loaded.input_shape)


def load_checkpoint_fp(path: Path) -> tuple:
    return _loaded_fingerprint(adapters.load_checkpoint(path))


def load_npz_fp(path: Path) -> tuple:
    ds = load_data(path)
    return tuple((a.dtype.str, a.shape, a.tobytes()) for a in (ds.x, ds.y))


def bundle_loader(key: np.ndarray, x: np.ndarray) -> Callable[[Path], tuple]:
    def load(path: Path) -> tuple:
        from prop_cli.bundle import load_bundle
        from prop_cli.run.policy import KeyedPolicy

        b = load_bundle(path)
        with warnings.catch_warnings(record=True) as caught:  # any warning is part of the outcome
            warnings.simplefilter("always")
            outs = tuple(KeyedPolicy(b, k)(x).tobytes() for k in (key, None))
        state = dict(b.loaded.module.state_dict())
        if b.keyed is not None:  # sealed bundles: the payload is in the records, behind the outputs
            state.update({f"enc:{k}": v for k, v in b.keyed.encoder.state_dict().items()})
        warned = sorted({type(w.message).__name__ for w in caught})
        return (json.dumps(b.manifest, sort_keys=True), outs, _tensors_digest(state), warned)

    load.key = key  # the CLI cases run the same key: a sealed record is read only when a key tries it
    return load


# ---- seeds --------------------------------------------------------------------------------------


def _mlp_tensors(sizes=(4, 16, 16, 2), seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        name: t
        for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:]))
        for name, t in ((f"{2 * i}.weight", torch.randn(b, a, generator=g) / a**0.5),
                        (f"{2 * i}.bias", torch.randn(b, generator=g) * 0.1))
    }  # fmt: skip


def _read_tree(root: Path, folder: str) -> dict[str, bytes]:
    files = sorted((root / folder).rglob("*"))
    return {str(p.relative_to(root)): p.read_bytes() for p in files if p.is_file()}


def _sb3_zip_bytes(work: Path) -> bytes:
    """A real Stable-Baselines3 PPO zip (deflated) where SB3 is installed, else one laid out like it."""
    try:
        from stable_baselines3 import PPO

        model = PPO("MlpPolicy", "Pendulum-v1", seed=0, device="cpu", policy_kwargs={"net_arch": [16, 16]})
        model.save(work / "ppo.zip")
        return (work / "ppo.zip").read_bytes()
    except ImportError:
        from tests.test_sb3 import make_zip

        return make_zip(work / "ppo.zip").read_bytes()


def make_seeds(work: Path, steps: int = 5) -> dict[str, list[Seed]]:
    """One valid input per kind (two checkpoints: safetensors and a torch .pt), built in ``work``."""
    from prop_cli.api import KeySource, personalize_checkpoint
    from prop_cli.config import PersonalizeConfig

    work.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    tensors = _mlp_tensors()
    save_file(tensors, str(work / "model.safetensors"), metadata={"activation": "relu"})
    torch.save(tensors, work / "model.pt")
    x = rng.uniform(-1, 1, (40, 4)).astype(np.float32)
    np.savez(work / "mine.npz", x=x, y=(-x[:, :2] * 0.5).astype(np.float32))
    key = rng.integers(0, 2, 128, dtype=np.uint8)
    cfg = PersonalizeConfig.of(steps=steps, encoder_hidden=[32], eval_random_keys=2)
    users = [(work / "mine.npz", KeySource(key, "file"))]
    personalize_checkpoint(str(work / "model.safetensors"), users, work / "b.prop", cfg)
    sealed_cfg = PersonalizeConfig.of(
        steps=steps, seal=True, payload="lora", payload_rank=2, eval_random_keys=2
    )
    personalize_checkpoint(str(work / "model.safetensors"), users, work / "s.prop", sealed_cfg)

    def one(kind: str, name: str, load: Callable, checksummed: bool, data: bytes | None = None) -> Seed:
        return Seed(kind, name, {name: data or (work / name).read_bytes()}, load, checksummed)

    seeds = {
        "bundle": [
            Seed("bundle", name, _read_tree(work, name), bundle_loader(key, x[:8]), True)
            for name in ("b.prop", "s.prop")  # unsealed and sealed
        ],
        "checkpoint": [
            one("checkpoint", "model.safetensors", load_checkpoint_fp, False),
            one("checkpoint", "model.pt", load_checkpoint_fp, True),  # zip: prop checks its CRC-32s
        ],
        "npz": [one("npz", "mine.npz", load_npz_fp, True)],
        "sb3": [one("sb3", "ppo.zip", load_checkpoint_fp, True, _sb3_zip_bytes(work))],
    }
    for group in seeds.values():
        for s in group:
            case = work / f"ref-{s.kind}-{s.name}"
            _write(case, s.files)
            s.reference = s.load(case / s.name)
    return seeds


# ---- mutations ----------------------------------------------------------------------------------


def _corrupt(data: bytes, how: str, rng: np.random.Generator) -> bytes | None:
    """``data`` damaged one way; None deletes the file."""
    n = len(data)
    if how == "delete":
        return None
    if how == "append":
        return data + rng.bytes(int(rng.integers(1, 64)))
    if n == 0:
        return b"\0"
    i = int(rng.integers(n))
    if how == "bitflip":
        return data[:i] + bytes([data[i] ^ (1 << int(rng.integers(8)))]) + data[i + 1 :]
    if how == "byte":
        return data[:i] + bytes([(data[i] + int(rng.integers(1, 256))) % 256]) + data[i + 1 :]
    if how == "truncate":
        return data[:i]
    if how == "zero":
        j = min(n, i + int(rng.integers(1, 65)))
        return data[:i] + bytes(j - i) + data[j:]
    raise ValueError(how)


def _json_paths(obj: object, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _json_paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += _json_paths(v, (*prefix, i))
    return out


def edit_json(obj: object, rng: np.random.Generator) -> object:
    """A copy of ``obj`` with one value replaced, one field removed or one unknown field added."""
    obj = json.loads(json.dumps(obj))
    paths = [p for p in _json_paths(obj) if p]
    path = paths[int(rng.integers(len(paths)))]
    parent = obj
    for part in path[:-1]:
        parent = parent[part]
    last, what = path[-1], int(rng.integers(10))
    if what == 0 and isinstance(parent, dict):
        del parent[last]
    elif what == 1 and isinstance(parent, dict):
        parent[f"unknown_{int(rng.integers(100))}"] = 1
    elif what == 2 and isinstance(parent[last], (int, float)) and not isinstance(parent[last], bool):
        parent[last] = parent[last] + int(rng.choice([-1, 1, 8, -8, 1000]))
    else:
        parent[last] = _ODD[int(rng.integers(len(_ODD)))]
    return obj


def _edit(seed: Seed, files: dict[str, bytes], rng: np.random.Generator) -> None:
    """A well-formed file with different content, as a hostile or careless editor would write it."""
    if seed.kind == "bundle":
        name = f"{seed.name}/{C.MANIFEST}"
        files[name] = dump_json(schema.stamp(edit_json(json.loads(files[name]), rng))).encode()
    elif seed.kind == "npz":
        with np.load(io.BytesIO(files[seed.name])) as z:
            arrays = {k: z[k] for k in z.files}
        k = list(arrays)[int(rng.integers(len(arrays)))]
        arrays[k] = _odd_array(arrays[k], rng)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        files[seed.name] = buf.getvalue()
    elif seed.kind == "sb3":
        src = zipfile.ZipFile(io.BytesIO(files[seed.name]))
        entries = {i.filename: src.read(i) for i in src.infolist()}
        entries["data"] = json.dumps(edit_json(json.loads(entries["data"]), rng)).encode()
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
            for name, data in entries.items():
                z.writestr(name, data)
        files[seed.name] = buf.getvalue()
    else:  # a checkpoint: one tensor replaced by an odd one
        tensors = _tensors_from_bytes(seed, files[seed.name])
        k = sorted(tensors)[int(rng.integers(len(tensors)))]
        odd = _odd_array(tensors[k].numpy(), rng)
        tensors[k] = torch.from_numpy(odd if odd.dtype.kind in "biuf" else np.zeros(3, np.uint8))
        files[seed.name] = _tensors_to_bytes(seed, tensors)


def _tensors_from_bytes(seed: Seed, data: bytes) -> dict[str, torch.Tensor]:
    if seed.name.endswith(".safetensors"):
        from safetensors.torch import load

        return dict(load(data))
    return dict(torch.load(io.BytesIO(data), weights_only=True))


def _tensors_to_bytes(seed: Seed, tensors: dict[str, torch.Tensor]) -> bytes:
    if seed.name.endswith(".safetensors"):
        from safetensors.torch import save

        return save({k: v.contiguous() for k, v in tensors.items()}, metadata={"activation": "relu"})
    buf = io.BytesIO()
    torch.save(tensors, buf)
    return buf.getvalue()


def _odd_array(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    choices = [
        lambda: a[: max(0, len(a) - 1)],  # one row short
        lambda: a.reshape(-1),  # flattened
        lambda: a.astype(np.float64),
        lambda: a.astype(np.int8),
        lambda: np.full_like(a, np.nan) if a.dtype.kind == "f" else a + 1,
        lambda: np.zeros((0, *a.shape[1:]), a.dtype),
        lambda: np.stack([a, a]),
        lambda: a.T.copy() if a.ndim == 2 else a[None],
        lambda: np.array(b"abc"),
        lambda: a * 1000,
    ]
    return np.asarray(choices[int(rng.integers(len(choices)))]())


def mutate(seed: Seed, how: str, rng: np.random.Generator) -> dict[str, bytes | None]:
    files: dict[str, bytes | None] = dict(seed.files)
    if how == EDIT:
        _edit(seed, files, rng)  # type: ignore[arg-type]
        return files
    names = sorted(seed.files)
    if how == "delete" and seed.kind != "bundle":
        how = "truncate"  # a single file deleted is "does not exist": not worth the cases
    name = names[int(rng.integers(len(names)))]
    files[name] = _corrupt(seed.files[name], how, rng)
    return files


# ---- running ------------------------------------------------------------------------------------


def _write(folder: Path, files: dict[str, bytes | None]) -> None:
    if folder.exists():
        shutil.rmtree(folder)
    for name, data in files.items():
        if data is not None:
            p = folder / name
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(data)
    folder.mkdir(parents=True, exist_ok=True)


def run_case(seed: Seed, how: str, rng: np.random.Generator, folder: Path) -> str:
    """One case: mutate, write, load; the outcome (see the module docstring)."""
    files = mutate(seed, how, rng)
    if files == seed.files:
        return "noop"  # e.g. zeros written over zeros: nothing to detect
    _write(folder, files)
    try:
        got = seed.load(folder / seed.name)
    except PropError as e:
        if "\n" in e.line():
            return "crash:multi-line PropError"
        return "error"
    except Exception as e:  # noqa: BLE001 - the point: anything else is a finding
        return f"crash:{type(e).__name__}"
    return "same" if got == seed.reference else "changed"


def allowed(seed: Seed, how: str, outcome: str) -> bool:
    """What the issue asks: no crash; no damaged bundle loads; `changed` only without a checksum."""
    if outcome.startswith("crash"):
        return False
    if how == EDIT or outcome == "noop":
        return True
    if seed.kind == "bundle":
        return outcome == "error"
    return outcome != "changed" or not seed.checksummed


def fuzz(
    seeds: list[Seed], cases: int, folder: Path, seed: int = 0, mutations: tuple[str, ...] = MUTATIONS
) -> tuple[Counter, list[tuple]]:
    """``cases`` seeded cases over ``seeds``: (counts by (seed name, mutation, outcome), the disallowed
    cases as (case number, seed name, mutation, outcome))."""
    rng = np.random.default_rng(seed)
    counts: Counter = Counter()
    bad: list[tuple] = []
    for i in range(cases):
        s = seeds[i % len(seeds)]
        how = mutations[int(rng.integers(len(mutations)))]
        case_rng = np.random.default_rng([seed, i])
        outcome = run_case(s, how, case_rng, folder)
        counts[(s.name, how, outcome)] += 1
        if not allowed(s, how, outcome):
            bad.append((i, s.name, how, outcome))
    return counts, bad
