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
    """``cfg`` (default: the settings the bundle was made with) as a sealed config, held to the bundle's
    payload kind, rank and layers: every record is enrolled in them. Built sealed: an unsealed setting
    the bundle recorded (--harden's, by bundles written before --seal --harden was refused) is not part
    of it, so nothing needs undoing."""
    m = bundle.manifest
    spec = m[C.M_PAYLOAD]
    settings = cfg.to_dict() if cfg is not None else m[C.M_CONFIG]
    layers = [x["name"] for x in spec["layers"]]
    cfg = PersonalizeConfig.from_dict({**settings, "seal": True, "layers": layers, "exclude": None})
    mode = cfg.mode
    rank = payload_kind(mode.payload).rank(mode.payload_rank)
    if (mode.payload, rank) != (spec["kind"], spec["rank"]):
        raise PropError(
            f"--payload {mode.payload} (rank {mode.payload_rank}) differs from the bundle's {spec['kind']} "
            f"(rank {spec['rank']})",
            "drop --payload/--payload-rank: every user of a bundle has the same payload layout",
        )
    return cfg


def train_added_user(
    bundle: Bundle, data: Dataset, bits: np.ndarray, cfg: PersonalizeConfig, device: str,
    progress: Progress | None,
) -> tuple[SealedRecord, dict, dict]:  # fmt: skip
    """The new user's sealed record, the manifest with it, and their report (as personalize prints it)."""
    m = bundle.manifest
    index = len(m[C.M_RECORDS])
    recipe = sealed_recipe(bundle.loaded)
    job = Job(bundle.loaded, cfg.train, cfg.mode, device, progress)
    [user], _, _ = recipe.train_users(job, [data], [bits], cfg.train.task or bundle.task, index)
    rec = seal_payload(next_version(m), user.private, user.payload, bits)  # the version it is written in
    new = with_records(m, [rec], [])
    state = SealedState(new, bundle.records.spec, [*bundle.records.records, rec], bundle.records.folder)
    report = user_report(state, recipe.report_view(bundle.loaded), user, bundle.task, cfg.train, index,
                         recipe.report_rows(cfg.train))  # fmt: skip
    return rec, new, report
