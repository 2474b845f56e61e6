"""What the sealed recipes (``sealed_array``, ``sealed_policy``) share: the payload layout, the per-user
report run through the records as anyone would run the bundle, and writing the bundle.

A sealed bundle's base is the original checkpoint; each user's payload (``prop_cli.core.payload``)
is trained on that user's data alone, with the base frozen, and sealed under their key. Users are
independent: ``add_user`` needs no one else's data or key. What it costs and what it does not
protect: docs/sealed.md.
"""

from __future__ import annotations

import contextlib
from abc import abstractmethod
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from prop_adapters import LoadedModel
from prop_cli import constants as C
from prop_cli.bundle import write_sealed
from prop_cli.bundle.records import SealedState
from prop_cli.config import PersonalizeConfig, SealedConfig, TrainConfig
from prop_cli.core import metrics
from prop_cli.core.key_files import kdf_record, new_salt
from prop_cli.core.key_sampling import one_bit_neighbours, random_keys
from prop_cli.core.layers import describe_layer, select_layers
from prop_cli.core.payload import PayloadSpec, payload_kind
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError

from .data import targets_tensor
from .frozen import held_autocast
from .recipe import Job, SealedRecipe, SealedUser, Trained, User, Written
from .report import eval_rng, outputs_report


def payload_spec(module: nn.Module, tc: TrainConfig, cfg: SealedConfig) -> PayloadSpec:
    mods = dict(module.named_modules())
    layers = [describe_layer(n, mods[n]) for n in select_layers(module, tc.layers, tc.exclude)]
    return PayloadSpec(cfg.payload, layers, payload_kind(cfg.payload).rank(cfg.payload_rank)).validate()


def check_distinct(keys: list[np.ndarray]) -> None:
    for i in range(len(keys)):
        for j in range(i + 1, len(keys)):
            if np.array_equal(keys[i], keys[j]):
                raise PropError(
                    f"users {i + 1} and {j + 1} have the same key",
                    "give each user their own key (prop keygen)",
                )


def private_report(
    o: torch.Tensor, p: torch.Tensor, b: torch.Tensor, task: str, losses: dict, job: Job[SealedConfig]
) -> dict:
    """What is sealed beside a user's payload: their validation figures and training settings."""
    return {
        "personalization": metrics.personalization(o, p, b, task),
        "user_leakage": metrics.leakage(o[None], p, b, task).item(),
        "samples": int(len(p)),
        "final_losses": losses,
        "config": PersonalizeConfig(job.train, job.mode).to_dict(),
    }


@torch.no_grad()
def sealed_report(
    state: SealedState,
    module: nn.Module,
    x: torch.Tensor,
    p: torch.Tensor,
    bits: np.ndarray,
    task: str,
    n_random: int,
    rng: np.random.Generator,
    per_forward: int | None = None,
) -> dict:
    """personalization of the user's key, and null, random and 1-bit keys run as a user would run
    them: each key tries every record, and the base runs when none opens (its outputs, computed once:
    the same module on the same inputs). ``per_forward``: rows per forward (None: all at once)."""

    def outputs(m: nn.Module) -> torch.Tensor:
        step = per_forward or len(x)
        return torch.cat([m(x[i : i + step]) for i in range(0, len(x), step)])

    b = outputs(module)

    def run(key: np.ndarray | None) -> torch.Tensor:
        opened = state.open(key) if key is not None else None
        return outputs(opened.payload.fold(module)) if opened is not None else b

    o_user = run(bits)
    o_null = run(None)[None]
    o_rand = torch.stack([run(k) for k in random_keys(n_random, len(bits), rng, exclude=bits)])
    o_ham = torch.stack([run(k) for k in one_bit_neighbours(bits)])
    return outputs_report(b, p, task, o_user, o_null, o_rand, o_ham)


def user_report(
    state: SealedState, view: nn.Module, user: SealedUser, task: str, tc: TrainConfig, index: int,
    per_forward: int | None = None,
) -> dict:  # fmt: skip
    """The report personalize and add-user print for one sealed user: their validation figures, and
    no key, random keys and 1-bit neighbours run through the records as anyone would run them. The
    training settings stay out (they are sealed with the payload); ``final_losses`` stays in."""
    x = torch.from_numpy(user.val.x)
    p = targets_tensor(user.val, task)
    rng = eval_rng(tc.seed, index)
    keys = sealed_report(state, view.eval(), x, p, user.bits, task, tc.eval_random_keys, rng, per_forward)
    return {**{k: v for k, v in user.private.items() if k != "config"}, **keys}


def public_layers(users: list[SealedUser], axes: dict[str, int]) -> list[dict]:
    """The manifest's ``keyed_layers`` of a sealed bundle (with batch axes that are not 0)."""
    return [
        {
            "name": x["name"],
            "features": x["in_features"],
            **({C.M_BATCH_AXIS: axes[x["name"]]} if axes.get(x["name"]) else {}),
        }
        for x in users[0].payload.spec.layers
    ]


@dataclass
class SealedResult(Trained):
    loaded: LoadedModel
    users: list[SealedUser]
    task: str
    axes: dict[str, int]
    tc: TrainConfig
    view: nn.Module  # what the reports run keys through
    input_shape: list | dict
    per_forward: int | None = None  # rows per forward of the report (None: all at once)

    def write(self, out: Path, manifest: dict, *, force: bool = False) -> Written:
        key = manifest[C.M_KEY]
        full = {
            **manifest,
            C.M_KEYED_LAYERS: public_layers(self.users, self.axes),
            C.M_PAYLOAD: self.users[0].payload.spec.to_dict(),
            # A sealed bundle always has a passphrase salt, so passphrase users can be added later.
            # No user count (the records list is the count) and no source (whether users chose
            # passphrases, which tells a guesser where to start).
            C.M_KEY: {
                **{k: v for k, v in key.items() if k != "source"},
                "kdf": key.get("kdf") or kdf_record(new_salt()),
            },
            C.M_TASK: self.task,
            C.M_IO: {"input_shape": self.input_shape, **manifest[C.M_IO]},
        }
        reports: list[dict] = []

        def manifest_metrics(state: SealedState) -> None:
            # The reports are printed for the user; none of a user's figures goes in the clear manifest.
            policy = self.loaded.policy
            memo = policy.memo() if policy is not None else contextlib.nullcontext()
            with memo, held_autocast(self.view, "cpu"):  # a base held bf16 (keep_dtypes): as in the steps
                for i, u in enumerate(self.users):
                    reports.append(user_report(state, self.view, u, self.task, self.tc, i, self.per_forward))

        users = [(u.payload, u.private, u.bits) for u in self.users]
        written = write_sealed(
            out, loaded=self.loaded, manifest=full, users=users, metrics=manifest_metrics, force=force
        )
        final = reports[0].pop("final_losses", {})
        for r in reports[1:]:
            r.pop("final_losses", None)
        return Written(written, reports, final)


class SealedRecipeBase(SealedRecipe):
    """``personalize`` of a sealed recipe: every user trained alone (``train_users``), then written."""

    @abstractmethod
    def input_shape(self, loaded: LoadedModel, val: Dataset) -> list | dict: ...

    def report_rows(self, tc: TrainConfig) -> int | None:
        """Rows per forward of the report (None: every held-out row at once)."""
        return None

    def personalize(
        self, job: Job[SealedConfig], users: list[User], general: Dataset | None = None
    ) -> SealedResult:
        if general is not None:
            raise PropError(
                "--general-data does nothing with --seal (the base stays the original)", "drop --general-data"
            )
        keys = [u.key_bits for u in users]
        check_distinct(keys)
        trained, task, axes = self.train_users(job, [u.data for u in users], keys, job.train.task)
        loaded = job.loaded
        view = self.report_view(loaded)
        shape = self.input_shape(loaded, trained[0].val)
        return SealedResult(loaded, trained, task, axes, job.train, view, shape, self.report_rows(job.train))
