"""Publisher signatures: `prop push --sign` signs what it uploads, `prop verify` checks a copy.

Signing and verifying are the OpenSSF ``model-signing`` library's (an optional extra, ``sign``), with
a private key (elliptic curve, PEM) or a key and its certificate chain; no sigstore, no network. The
signature (``model.sig``, a sigstore bundle) covers every file of the folder as uploaded (the model
card included, which says the bundle is signed): change, add or remove any byte of any file and
verification fails.

What a signature proves: the files are the ones the holder of that private key published. What it
does not: that the publisher is who you think (compare the key's fingerprint or the certificate with
one you got from them another way), that the bundle behaves well, or anything about a user's key:
a user's key authenticates their own behaviour (``prop_cli.bundle.enrol``), the signature the rest.
Nor, alone, that it is the publisher's latest revision: the signature covers the manifest and so its
bundle version, and ``prop verify`` refuses a version older than one it verified here from the same
publisher (``check_revision``; ``prop_cli.bundle.rollback``).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from prop_cli import constants as C
from prop_cli.errors import PropError, brief

SIGNATURE = C.SIGNATURE_FILE
SIGN_EXTRA = "pip install 'prop-keys[sign]'"
# Not part of what was published: huggingface_hub's bookkeeping in a `hf download --local-dir` copy
# (model-signing itself leaves out .git, .gitattributes, .github and .gitignore).
IGNORED = (".cache", C.BUNDLE_LOCK)  # the lock file a writer holds (files/lock.py): not the bundle's


def _lib():
    try:
        from model_signing import hashing, signing, verifying
    except ImportError as e:
        raise PropError(f"signatures need the 'sign' extra ({e.name} is not installed)", SIGN_EXTRA) from None
    return hashing, signing, verifying


def require_signing() -> None:
    """Fail before any work when --sign cannot sign (model-signing is the extra `sign`)."""
    _lib()


def _read(path: Path, flag: str) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as e:
        raise PropError(f"{flag} {path} cannot be read ({e.strerror})", "check the path") from None


def fingerprint(key_path: Path, flag: str = "--sign") -> str:
    """``sha256:<hex>`` of a PEM key's public part (SubjectPublicKeyInfo, DER): what people compare."""
    from cryptography.hazmat.primitives import serialization

    data = _read(key_path, flag)
    try:
        key = serialization.load_pem_private_key(data, password=None).public_key()
    except (ValueError, TypeError):
        try:
            key = serialization.load_pem_public_key(data)
        except ValueError:
            raise PropError(
                f"{flag} {key_path} is not an unencrypted PEM elliptic-curve key",
                "make one with: openssl ecparam -name prime256v1 -genkey -noout -out publisher.pem",
            ) from None
    der = key.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
    return "sha256:" + hashlib.sha256(der).hexdigest()


def signed_note(private_key: Path, certificate: Path | None = None) -> str:
    """The model card's line about the signature (written before signing: the card is signed too)."""
    who = f"certificate `{Path(certificate).name}`" if certificate else "an elliptic-curve key"
    return (
        f"yes: every file here is signed ({SIGNATURE}, OpenSSF model-signing) with {who}, public key "
        f"`{fingerprint(private_key)}`. Check it with `prop verify DIR --public-key PUBLISHER.pub` and "
        "compare that fingerprint with one the publisher gave you another way"
    )


def _hashing(hashing, folder: Path):
    paths = [folder / p for p in (*IGNORED, SIGNATURE)]
    return hashing.Config().set_ignored_paths(paths=paths, ignore_git_paths=True)


def sign_folder(
    folder: Path, private_key: Path, certificate: Path | None = None, chain: list[Path] | tuple = ()
) -> Path:
    """Sign every file of ``folder`` into ``folder/model.sig``."""
    hashing, signing, _ = _lib()
    folder = Path(folder)
    fingerprint(private_key)  # a clear error for a bad key before the library's
    cfg = signing.Config()
    try:
        if certificate is not None:
            cfg = cfg.use_certificate_signer(
                private_key=private_key, signing_certificate=certificate, certificate_chain=list(chain)
            )
        else:
            cfg = cfg.use_elliptic_key_signer(private_key=private_key)
        cfg.set_hashing_config(_hashing(hashing, folder)).sign(folder, folder / SIGNATURE)
    except (ValueError, TypeError, OSError) as e:
        raise PropError(f"cannot sign {folder} with {private_key} ({brief(e)})", "check the key") from None
    return folder / SIGNATURE


def verify_folder(folder: Path, public_key: Path | None = None, chain: list[Path] | tuple = ()) -> dict:
    """Check ``folder/model.sig`` against every file of ``folder``; a PropError names what failed."""
    hashing, _, verifying = _lib()
    folder = Path(folder)
    sig = folder / SIGNATURE
    if (public_key is None) == (not chain):
        raise PropError("verify needs one of --public-key and --certificate-chain", "pass the publisher's")
    if not sig.is_file():
        raise PropError(f"{folder} is not signed (no {SIGNATURE})", "ask the publisher for a signed copy")
    cfg = verifying.Config()
    cfg = (
        cfg.use_elliptic_key_verifier(public_key=public_key)
        if public_key is not None
        else cfg.use_certificate_verifier(certificate_chain=list(chain))
    )
    try:
        cfg.set_hashing_config(_hashing(hashing, folder)).verify(folder, sig)
    except Exception as e:  # noqa: BLE001 - the library raises ValueError and its own errors alike
        raise PropError(
            f"the signature of {folder} does not verify: {brief(e, 200)}",
            "do not use these files: they are not what the key's holder signed (or the wrong key was given)",
        ) from None
    signer = fingerprint(public_key, "--public-key") if public_key is not None else "certificate chain"
    who = signer_id(public_key, chain)
    return {"folder": str(folder), "signature": SIGNATURE, "signer": signer, "signer_id": who}


def signer_id(public_key: Path | None, chain: list[Path] | tuple = ()) -> str:
    """Whom versions are remembered for: the public key's fingerprint, or the digest of the certificate
    chain given (the roots trusted), so that one publisher's revisions are compared with each other."""
    if public_key is not None:
        return fingerprint(public_key, "--public-key")
    h = hashlib.sha256()
    for c in chain:
        h.update(hashlib.sha256(_read(c, "--certificate-chain")).digest())
    return "chain sha256:" + h.hexdigest()


def check_revision(folder: Path, manifest: dict, signer: str, allow_rollback: bool = False) -> bool:
    """After a signature verified: refuse a bundle version older than one verified on this machine from
    the same ``signer`` (``allow_rollback``: a warning), and remember this one. False: a format 1-4
    bundle, which has no version to compare."""
    from prop_cli.bundle.rollback import verified

    return verified(manifest, signer, f"{folder}", allow_rollback)
