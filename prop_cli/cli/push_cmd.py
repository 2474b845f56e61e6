from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from prop_cli.errors import plural

from .common import err, fail, out, print_json
from .options import BundleArg, Json, OnnxDir


def push(
    bundle: BundleArg,
    repo: Annotated[
        str, typer.Argument(metavar="REPO", help="Hub model repo, <org or user>/<name> (created if missing).")
    ],
    private: Annotated[bool, typer.Option("--private", help="Create the repo as private.")] = False,
    revision: Annotated[
        str | None, typer.Option("--revision", help="Branch to push to (created if missing).")
    ] = None,
    onnx_dir: OnnxDir = None, as_json: Json = False,
    allow_unsealed: Annotated[
        bool, typer.Option("--allow-unsealed", help="Publish an unsealed bundle to a public repo anyway.")
    ] = False,
    sign: Annotated[Path | None, typer.Option("--sign", help="Sign every uploaded file with this private "
                                              "key (PEM, elliptic curve; prop-keys[sign]).")] = None,
    certificate: Annotated[Path | None, typer.Option("--certificate", help="With --sign: the key's "
                                                     "certificate (certificate signing).")] = None,
    chain: Annotated[list[Path] | None, typer.Option("--certificate-chain", help="With --certificate: "
                                                     "the chain up to its root; repeat.")] = None,
) -> None:  # fmt: skip
    """Upload a bundle (and its ONNX export) to the Hugging Face hub with a generated model card."""
    from prop_cli.api import push_bundle

    if (certificate is not None or chain) and sign is None:
        fail("--certificate and --certificate-chain sign with --sign's key", "pass --sign KEY.pem")
    result = push_bundle(
        bundle, repo, private=private, revision=revision, onnx_dir=onnx_dir, allow_unsealed=allow_unsealed,
        sign=sign, certificate=certificate, chain=chain or (), progress=lambda line: err.print(line),
    )  # fmt: skip
    if as_json:
        print_json(
            {"repo": result.repo_id, "url": result.url, "files": result.files, "revision": result.revision}
        )
        return
    out.print(
        f"pushed {plural(len(result.files), 'file')} to {result.url}"
        + (f" ({result.revision})" if result.revision else "")
    )
