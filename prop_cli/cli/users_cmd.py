"""`prop add-user` and `prop remove-user`: users of a sealed bundle, one at a time."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from prop_cli.config import PersonalizeConfig, cli_settings
from prop_cli.constants import DEFAULT_DEVICE
from prop_cli.errors import plural

from .common import err, fail, out, print_json, read_passphrase, training_progress, warn
from .options import (
    BundleArch,
    BundleArg,
    Device,
    Json,
    KeyFile,
    Passphrase,
    TrustRemoteCode,
    WeakPassphrase,
    settings_options,
)

# add-user trains like personalize --seal; these settings may differ from the bundle's.
SETTINGS = cli_settings("steps", "payload_lr", "val_fraction", "seed")


def _key(bundle: Path, key_file: Path | None, passphrase: bool, required: bool, new: bool = False,
         allow_weak: bool = False):  # fmt: skip
    from prop_cli.api import check_passphrase, key_for_bundle, read_manifest

    if key_file is None and not passphrase:
        if required:
            fail("no key given", "pass --key-file (make one with prop keygen) or --passphrase")
        return None
    phrase = read_passphrase() if passphrase else None
    if new and phrase is not None:  # a new user's passphrase: how long it holds against guessing
        check_passphrase(phrase, "the new user's passphrase", allow_weak)
    return key_for_bundle(read_manifest(bundle), key_file, phrase)


@settings_options(SETTINGS, dict)
def add_user(
    bundle: BundleArg,
    data: Annotated[Path, typer.Option("--data", help="The new user's data (x, y).")],
    config: dict,
    key_file: KeyFile = None,
    passphrase: Passphrase = False,
    device: Device = DEFAULT_DEVICE,
    as_json: Json = False,
    trust_remote_code: TrustRemoteCode = False,
    weak_passphrase: WeakPassphrase = False,
    arch: BundleArch = None,
) -> None:
    """Add a user to a sealed bundle, with their data and key only (no one else's)."""
    from prop_cli.api import KeySource, read_manifest
    from prop_cli.api import add_user as api_add_user

    bits = _key(bundle, key_file, passphrase, required=True, new=True, allow_weak=weak_passphrase)
    given = {k: v for k, v in config.items() if v != SETTINGS[k][1]}  # the flags on this command line
    # The bundle's settings, except those; built sealed (train.added_user holds them to the bundle's payload).
    base = PersonalizeConfig.from_dict({**read_manifest(bundle).get("config", {}), **given, "seal": True})
    result = training_progress(
        lambda cb: api_add_user(
            bundle, data, KeySource(bits, "passphrase" if passphrase else "file"), cfg=base, device=device,
            progress=cb, trust_remote_code=trust_remote_code, arch=arch,
        ),
        base.train.steps, "add-user",
    )  # fmt: skip
    if as_json:
        print_json({"bundle": str(result.bundle), "record": result.record, "users": result.users,
                    "metrics": result.metrics, "onnx_export": result.export})  # fmt: skip
        _export_note(result)
        return
    m = result.metrics
    out.print(
        f"added record {result.record} to {result.bundle} ({plural(result.users, 'user')}): personalization "
        f"{m['personalization']:.4f} on {m['samples']} validation samples; wrong keys: null, "
        f"{m['random']['leakage']['n']} random and {m['hamming1']['leakage']['n']} 1-bit keys, worst leakage "
        f"{max(m[g]['leakage']['worst'] for g in ('null', 'random', 'hamming1')):.4f}"
    )
    _export_note(result)


def _export_note(result) -> None:
    """What became of the bundle's ONNX export (stderr): it holds the new record, or it is out of date."""
    e = result.export
    if e is None:
        return
    if e["current"]:
        err.print(
            f"the ONNX export in {e['folder']} now holds the new record; it runs the new user's behaviour "
            f"once bound to their key: prop export {result.bundle} --onnx --key-file KEY --force"
        )
    else:
        warn(f"the ONNX export in {e['folder']} no longer matches the bundle ({e['why']}): "
             f"{e['fix'].replace('BUNDLE', str(result.bundle))}")  # fmt: skip


def remove_user(
    bundle: BundleArg,
    key_file: KeyFile = None,
    passphrase: Passphrase = False,
    record: Annotated[
        str | None,
        typer.Option("--record", help="Remove this record id without its key (for a lost key)."),
    ] = None,
    as_json: Json = False,
    trust_remote_code: TrustRemoteCode = False,
    arch: BundleArch = None,
) -> None:
    """Remove a user from a sealed bundle (and its ONNX export): the one your key opens (or --record ID)."""
    from prop_cli.api import remove_user as api_remove_user

    bits = _key(bundle, key_file, passphrase, required=record is None)
    result = api_remove_user(bundle, key=bits, record=record, trust_remote_code=trust_remote_code, arch=arch)
    if as_json:
        print_json({"bundle": str(result.bundle), "record": result.record, "users": result.users})
        return
    left = f"{plural(result.users, 'user')} left"
    err.print(f"removed record {result.record} from {result.bundle} ({left})")
