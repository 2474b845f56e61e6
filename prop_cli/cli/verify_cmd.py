"""`prop verify`: a downloaded bundle's publisher signature, and `prop enrol`: your key in a bundle."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from prop_cli.errors import plural

from .common import fail, out, print_json, read_passphrase
from .options import BundleArg, Json, KeyFile, Passphrase, TrustRemoteCode, opt

PublicKey = Annotated[Path | None, opt("--public-key", "The publisher's public key (PEM).")]
AllowRevision = Annotated[
    bool,
    opt("--allow-rollback", "Accept a revision older than one this machine verified from the same "
                            "publisher (with a warning)."),
]  # fmt: skip
Chain = Annotated[
    list[Path] | None, opt("--certificate-chain", "Certificates up to a root you trust (PEM); repeat.")
]


def verify(
    folder: Annotated[
        Path, typer.Argument(metavar="FOLDER", help="A signed bundle folder (e.g. from hf download).")
    ],
    public_key: PublicKey = None, chain: Chain = None, as_json: Json = False,
    allow_rollback: AllowRevision = False,
) -> None:  # fmt: skip
    """Check that every file of FOLDER is what the publisher signed (prop push --sign), and that it is not
    older than a revision verified here before; nothing runs."""
    from prop_cli.api import verify_bundle

    result = verify_bundle(folder, public_key=public_key, chain=chain or (), allow_rollback=allow_rollback)
    if as_json:
        print_json(result)
        return
    version = f"version {result['bundle_version']}" if result["rollback_checked"] else "no bundle version"
    out.print(
        f"verified {result['folder']}: every file is as signed by {result['signer']} ({result['mode']} "
        f"bundle, format {result['format']}, {version}, {plural(result['users'], 'user')})"
    )


def enrol(
    bundle: BundleArg, key_file: KeyFile = None, passphrase: Passphrase = False, as_json: Json = False,
    trust_remote_code: TrustRemoteCode = False,
) -> None:  # fmt: skip
    """Enrol your key in an unsealed bundle as it is now (a format 1-3 bundle you trust, or a change you
    accept): from then on your key runs it."""
    from prop_cli.api import enrol as api_enrol
    from prop_cli.api import key_for_bundle, read_manifest

    if key_file is None and not passphrase:
        fail("no key given", "pass --key-file or --passphrase")
    bits = key_for_bundle(read_manifest(bundle), key_file, read_passphrase() if passphrase else None)
    result = api_enrol(bundle, bits, trust_remote_code=trust_remote_code)
    if as_json:
        print_json({"bundle": str(result.bundle), "status": result.status, "format": result.format_version})
        return
    out.print(f"{result.status}: {result.bundle} (format {result.format_version})")
