"""One more user of a sealed bundle (`prop add-user`): their payload trained on their data alone, in the
bundle's own payload layout, sealed into a record. No other user's data or key is needed."""

from __future__ import annotations

import numpy as np

from prop_cli import constants as C
from prop_cli.bundle import Bundle
from prop_cli.bundle.manifest import next_version
from prop_cli.bundle.records import SealedRecord, SealedState, seal_payload, with_records
from prop_cli.config import PersonalizeConfig
from prop_cli.core.payload import payload_kind
from prop_cli.datasources import Dataset
from prop_cli.errors import PropError

from .choose import sealed_recipe
from .recipe import Job, Progress
from .sealed import user_report


def added_user_config(bundle: Bundle, cfg: PersonalizeConfig | None) -> PersonalizeConfig:
    """``cfg`` (default: the settings the bundle was made with), held to the bundle's payload kind, rank
    and layers: every record is enrolled in them."""
    m = bundle.manifest
    cfg = cfg or PersonalizeConfig.from_dict(m[C.M_CONFIG])
    spec = m[C.M_PAYLOAD]
    rank = payload_kind(cfg.payload).rank(cfg.payload_rank)
    if (cfg.payload, rank) != (spec["kind"], spec["rank"]):
        raise PropError(
            f"--payload {cfg.payload} (rank {cfg.payload_rank}) differs from the bundle's {spec['kind']} "
            f"(rank {spec['rank']})",
            "drop --payload/--payload-rank: every user of a bundle has the same payload layout",
        )
    cfg.layers = [x["name"] for x in spec["layers"]]
    cfg.exclude = None
    cfg.seal = True
    # A sealed record trains none of --harden's settings; bundles written before --seal --harden was
    # refused recorded them anyway, and their own add-user must not be refused for it.
    cfg.without_hardening()
    return cfg.validate(key_bits=bundle.key_bits)


def train_added_user(
    bundle: Bundle, data: Dataset, bits: np.ndarray, cfg: PersonalizeConfig, device: str,
    progress: Progress | None,
) -> tuple[SealedRecord, dict, dict]:  # fmt: skip
    """The new user's sealed record, the manifest with it, and their report (as personalize prints it)."""
    m = bundle.manifest
    index = len(m[C.M_RECORDS])
    recipe = sealed_recipe(bundle.loaded)
    job = Job(bundle.loaded, cfg, device, progress)
    [user], _, _ = recipe.train_users(job, [data], [bits], cfg.task or bundle.task, index)
    rec = seal_payload(next_version(m), user.private, user.payload, bits)  # the version it is written in
    new = with_records(m, [rec], [])
    state = SealedState(new, bundle.records.spec, [*bundle.records.records, rec])
    report = user_report(state, recipe.report_view(bundle.loaded), user, bundle.task, cfg, index,
                         recipe.report_rows(cfg))  # fmt: skip
    return rec, new, report
