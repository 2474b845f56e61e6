"""Sealed bundles: the public base is the original checkpoint, each user's payload is encrypted.

Nothing in a sealed bundle's files gives a path from a key to the user's behaviour: the base weights
are the original's, byte for byte where the checkpoint was safetensors, and each user's payload
(``prop_cli.payload``: a low-rank update, a delta, or new weights of the keyed layers) is an AES-GCM
record (``prop_cli.seal``) that only their key opens. A wrong key opens nothing, and the bundle runs
the base: exactly the original. Users are independent: each payload is trained on its user's data
alone, so ``add_user`` needs no one else's data or key and ``remove_user`` leaves the others intact.

What it costs, measured (docs/sealed.md): personalization against unsealed PRoP on IL, digits and
reach; what it does not protect: whoever holds a user's key (or the decrypted policy in memory).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from prop_adapters import LoadedModel

from . import constants as C
from . import data as data_mod
from . import metrics
from .config import PersonalizeConfig
from .errors import PropError
from .evaluate import outputs_report
from .files import dump_json, sha256_file
from .keyspace import one_bit_neighbours, random_keys
from .layers import select_layers
from .objective import row_loss
from .optim import Adam, cosine_lr
from .payload import Payload, PayloadSpec
from .seal import SealedRecord, decode_payload, encode_payload, open_record, seal

Progress = Callable[[int, dict[str, float]], None]

# The manifest fields that decide how a payload is applied; the cipher authenticates them with every
# record (associated data), so an edit to any of them makes every record fail to open. Metrics,
# config, the audit summary and the records list are informational and may change (add-user, attack
# --record) without re-encrypting anyone's record.
_BOUND = (C.M_FORMAT, C.M_MODE, C.M_MODEL, C.M_PAYLOAD, C.M_TASK)


def public_part(manifest: dict) -> dict:
    """The manifest fields that opening a record needs (an ONNX export carries them)."""
    part = {f: manifest.get(f) for f in _BOUND}
    part.update({C.M_IO: manifest[C.M_IO], C.M_KEY: manifest[C.M_KEY], C.M_FILES: manifest[C.M_FILES]})
    part[C.M_RECORDS] = manifest[C.M_RECORDS]
    return part


def binding(manifest: dict, record_id: str) -> bytes:
    """The associated data of one record: a digest of the bundle's bound public fields and its id."""
    key = manifest[C.M_KEY]
    bound = {f: manifest.get(f) for f in _BOUND}
    bound["input_shape"] = manifest[C.M_IO]["input_shape"]
    bound["key"] = {"bits": key["bits"], "kdf": key.get("kdf")}
    bound["base_sha256"] = manifest[C.M_FILES][C.BASE_WEIGHTS]
    bound["record"] = record_id
    text = json.dumps(bound, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(b"prop/seal/binding/v1\0" + text.encode()).digest()


def payload_spec(module: torch.nn.Module, cfg: PersonalizeConfig) -> PayloadSpec:
    mods = dict(module.named_modules())
    names = select_layers(module, cfg.layers, cfg.exclude)
    layers = [
        {"name": n, "in_features": mods[n].in_features, "out_features": mods[n].out_features} for n in names
    ]
    return PayloadSpec(cfg.payload, layers, cfg.payload_rank if cfg.payload == "lora" else 0).validate()


@dataclass
class TrainedPayload:
    payload: Payload
    report: dict  # evaluate-style: personalization and the wrong keys' leakage and fidelity
    final_losses: dict[str, float]


def train_payload(
    module: torch.nn.Module,
    spec: PayloadSpec,
    train: data_mod.Dataset,
    task: str,
    cfg: PersonalizeConfig,
    dev: torch.device,
    progress: Progress | None = None,
) -> tuple[Payload, dict[str, float]]:
    """Fit one user's payload on their data, the base frozen (it stays the original)."""
    from .trainer import targets_tensor

    gen = torch.Generator().manual_seed(cfg.seed)
    payload = Payload(spec, gen).to(dev)
    x = torch.from_numpy(train.x).to(dev)
    y = targets_tensor(train, task).to(dev)
    rng = np.random.default_rng(cfg.seed)
    opt = Adam(list(payload.parameters()), lr=cfg.payload_lr)
    losses: dict[str, float] = {}
    module.requires_grad_(False)
    with payload.attached(module) as m:
        for step in range(cfg.steps):
            opt.set_lr_factor(cosine_lr(1.0, step, cfg.steps, cfg.lr_floor))
            idx = torch.from_numpy(rng.integers(0, len(x), cfg.user_rows)).to(dev)
            loss = row_loss(m(x[idx]), y[idx], task, distill=False).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses = {"personal": loss.item()}
            if progress is not None:
                progress(step + 1, losses)
    return payload.eval(), losses


@torch.no_grad()
def sealed_report(
    state: SealedState,
    module: torch.nn.Module,
    x: torch.Tensor,
    p: torch.Tensor,
    bits: np.ndarray,
    task: str,
    n_random: int,
    rng: np.random.Generator,
) -> dict:
    """personalization of the user's key, and null, random and 1-bit keys run as a user would run
    them: each key tries every record, and the base runs when none opens."""
    b = module(x)

    def run(key: np.ndarray | None) -> torch.Tensor:
        opened = state.open(key) if key is not None else None
        return opened.payload.fold(module)(x) if opened is not None else module(x)

    o_user = run(bits)
    o_null = run(None)[None]
    o_rand = torch.stack([run(k) for k in random_keys(n_random, len(bits), rng, exclude=bits)])
    o_ham = torch.stack([run(k) for k in one_bit_neighbours(bits)])
    return outputs_report(b, p, task, o_user, o_null, o_rand, o_ham)


# --- records in a bundle -------------------------------------------------------------------------


@dataclass
class Opened:
    record_id: str
    payload: Payload
    meta: dict  # what was sealed beside the tensors: the user's metrics and training settings


@dataclass
class SealedState:
    """A sealed bundle's public part beyond the base: the payload layout and the encrypted records."""

    manifest: dict
    spec: PayloadSpec
    records: list[SealedRecord]

    def __post_init__(self) -> None:
        # The associated data of each record, computed once: the audit tries a million keys.
        self._bound = [binding(self.manifest, rec.id) for rec in self.records]

    def open(self, bits: np.ndarray) -> Opened | None:
        """The user's payload if ``bits`` opens one of the records, else None (a wrong key)."""
        for rec, bound in zip(self.records, self._bound):
            data = open_record(rec, bits, bound)
            if data is not None:
                tensors, meta = decode_payload(data)
                return Opened(rec.id, Payload.from_tensors(self.spec, tensors).eval(), meta)
        return None


def record_entry(rec: SealedRecord, file_sha256: str) -> dict:
    return {
        "id": rec.id,
        "file": f"{C.RECORDS_DIR}/{rec.id}{C.RECORD_SUFFIX}",
        "salt": rec.salt.hex(),
        "nonce": rec.nonce.hex(),
        "sha256": file_sha256,
    }


def _bad(path: Path, what: str) -> PropError:
    return PropError(f"bundle {path}: {what}", "restore the bundle from a trusted copy")


def load_state(path: Path, manifest: dict) -> SealedState:
    """The records of a sealed bundle, each file checked against its sha256 in the manifest."""
    spec = PayloadSpec.from_dict(manifest[C.M_PAYLOAD])
    records = []
    for entry in manifest[C.M_RECORDS]:
        f = path / entry["file"]
        if Path(entry["file"]).parent.name != C.RECORDS_DIR or not f.is_file():
            raise _bad(path, f"user record {entry['file']} is missing")
        if sha256_file(f) != entry["sha256"]:
            raise _bad(
                path, f"{entry['file']} does not match its sha256 in {C.MANIFEST} (modified or corrupt)"
            )
        records.append(
            SealedRecord(
                entry["id"], bytes.fromhex(entry["salt"]), bytes.fromhex(entry["nonce"]), f.read_bytes()
            )
        )
    return SealedState(manifest, spec, records)


def seal_payload(manifest: dict, opened_meta: dict, payload: Payload, bits: np.ndarray) -> SealedRecord:
    """Encrypt one user's payload (and their metrics, which stay private too) for their key."""
    plaintext = encode_payload(payload.tensors(), opened_meta)
    return seal(plaintext, bits, lambda rid: binding(manifest, rid))


def write_record(folder: Path, rec: SealedRecord) -> str:
    """Write a record's ciphertext under ``folder``; returns its sha256."""
    f = folder / C.RECORDS_DIR / f"{rec.id}{C.RECORD_SUFFIX}"
    f.parent.mkdir(exist_ok=True)
    f.write_bytes(rec.ciphertext)
    return sha256_file(f)


def rewrite_records(bundle: Path, manifest: dict, add: list[SealedRecord], drop: list[str]) -> dict:
    """Add and remove records of a sealed bundle in place. The manifest is swapped atomically after the
    new files exist and before old ones are deleted, so an interruption leaves a loadable bundle."""
    from .files import write_text
    from .manifest import restamp

    new = dict(manifest)
    entries = [e for e in manifest[C.M_RECORDS] if e["id"] not in drop]
    for rec in add:
        entries.append(record_entry(rec, write_record(bundle, rec)))
    new[C.M_RECORDS] = entries
    if new.get(C.M_METRICS):
        users = [u for u in new[C.M_METRICS].get("users", []) if u.get("record") not in drop]
        new[C.M_METRICS] = {**new[C.M_METRICS], "users": users}
    new = restamp(new)
    write_text(bundle / C.MANIFEST, dump_json(new), what="manifest", flag="BUNDLE")
    for e in manifest[C.M_RECORDS]:
        if e["id"] in drop:
            (bundle / e["file"]).unlink(missing_ok=True)
    return new


def copy_records(src: Path, dst: Path, manifest: dict) -> None:
    """Copy a sealed bundle's record files (for exports: the ONNX runtime opens them too)."""
    (dst / C.RECORDS_DIR).mkdir(parents=True, exist_ok=True)
    for e in manifest[C.M_RECORDS]:
        shutil.copyfile(src / e["file"], dst / e["file"])


def check_new_key(state: SealedState, bits: np.ndarray) -> None:
    if state.open(bits) is not None:
        raise PropError(
            "this key already opens a user of the bundle",
            "use prop remove-user first to replace that user, or give the new user their own key",
        )


def check_distinct(keys: list[np.ndarray]) -> None:
    for i in range(len(keys)):
        for j in range(i + 1, len(keys)):
            if np.array_equal(keys[i], keys[j]):
                raise PropError(
                    f"users {i + 1} and {j + 1} have the same key",
                    "give each user their own key (prop keygen)",
                )


@dataclass
class SealedUser:
    payload: Payload
    private: dict  # sealed with the payload: the user's personalization and training settings
    bits: np.ndarray
    val: data_mod.Dataset


def train_users(
    loaded: LoadedModel,
    datasets: list[data_mod.Dataset],
    keys: list[np.ndarray],
    task: str | None,
    cfg: PersonalizeConfig,
    device: str = "cpu",
    progress: Progress | None = None,
    first_index: int = 0,
) -> tuple[list[SealedUser], str, dict[str, int]]:
    """Each user's payload on their own data alone (users are independent), with its validation figure.
    Returns the users, the task (``task``: an override) and the keyed layers' batch axes (policies)."""
    from .trainer import User, _prepare, resolve_device, targets_tensor

    if loaded.policy is not None:  # LeRobot: the policy's own loss on dict batches
        from .policy_trainer import train_policy_payloads

        users, axes = train_policy_payloads(loaded, datasets, keys, cfg, device, progress, first_index)
        return users, "regression", axes
    datasets, task = _prepare(loaded, [User(d, b) for d, b in zip(datasets, keys)], None, task)
    dev = resolve_device(device)
    module = loaded.module.to(dev).eval()
    spec = payload_spec(module, cfg)
    out = []
    for i, (ds, bits) in enumerate(zip(datasets, keys), first_index):
        tr, val = data_mod.split(ds, cfg.val_fraction, cfg.seed + i)
        payload, losses = train_payload(module, spec, tr, task, cfg, dev, progress)
        xv, pv = torch.from_numpy(val.x).to(dev), targets_tensor(val, task).to(dev)
        with torch.no_grad():
            o, b = payload.fold(module)(xv), module(xv)
        private = {
            "personalization": metrics.personalization(o, pv, b, task),
            "user_leakage": metrics.leakage(o[None], pv, b, task).item(),
            "samples": len(val),
            "final_losses": losses,
            "config": cfg.to_dict(),
        }
        out.append(SealedUser(payload.to("cpu"), private, bits, val))
    module.to("cpu")
    return out, task, {}


def user_report(bundle, user: SealedUser, cfg: PersonalizeConfig, index: int) -> dict:
    """The report personalize and add-user print for one sealed user: their validation figures, and
    no key, random keys and 1-bit neighbours run through the written bundle as anyone would run them.
    The training settings stay out (they are sealed with the payload); ``final_losses`` stays in."""
    from .trainer import _EVAL_STREAM, targets_tensor

    x = torch.from_numpy(user.val.x)
    p = targets_tensor(user.val, bundle.task)
    rng = np.random.default_rng((cfg.seed, _EVAL_STREAM, index))
    module = bundle.loaded.module.eval()
    keys = sealed_report(bundle.sealed, module, x, p, user.bits, bundle.task, cfg.eval_random_keys, rng)
    return {**{k: v for k, v in user.private.items() if k != "config"}, **keys}


def public_metrics(report: dict, record_id: str) -> dict:
    """What of a sealed user's report goes into the manifest: the wrong keys' figures only (their
    personalization is sealed in their record)."""
    return {"record": record_id, **{k: report[k] for k in ("samples", "null", "random", "hamming1")}}
