from __future__ import annotations

from pathlib import Path

from prop_cli.errors import plural

from .common import checkpoint_options, out, print_json
from .options import (
    Activation,
    Arch,
    ArchKwargs,
    Checkpoint,
    Exclude,
    Json,
    Layers,
    TrustRemoteCode,
    bundle_folder,
)


def inspect(
    checkpoint: Checkpoint, arch: Arch = None, arch_kwargs: ArchKwargs = None, activation: Activation = None,
    layers: Layers = None, exclude: Exclude = None, as_json: Json = False,
    trust_remote_code: TrustRemoteCode = False,
) -> None:  # fmt: skip
    """List the linear layers and convolutions of a checkpoint, which ones would be keyed (and their share of
    the parameters), and what prop knows of it. Given a bundle: its mode, users, keyed layers, recorded
    audit and signature."""
    from rich.table import Table

    from prop_cli.api import describe_bundle, inspect_checkpoint, is_bundle

    if is_bundle(str(bundle_folder(Path(checkpoint)))):
        info = describe_bundle(str(bundle_folder(Path(checkpoint))))
        print_json(info) if as_json else out.print(_bundle_table(info))
        return

    opts = checkpoint_options(arch, arch_kwargs, activation, trust_remote_code)
    info = inspect_checkpoint(checkpoint, opts, layers, exclude)
    if as_json:
        print_json(info)
        return
    model = info["model"]
    known = ", ".join(f"{k} {v}" for k, v in model.items() if k != "adapter" and v is not None)
    keyed = f"{info['keyed_parameters']:,} keyed ({100 * info['keyed_share']:.1f}%)"
    size = f"{info['parameters']:,} parameters, {keyed}"
    table = Table(
        title=f"{Path(checkpoint).name}: {info['adapter']} adapter, {size}" + (f"\n{known}" if known else ""),
        title_justify="left",
    )
    for col in ("layer", "kind", "in", "out", "parameters", "keyed"):
        table.add_column(col, overflow="fold")  # narrow: a long name folds onto more lines, never cut
    for layer in info["layers"]:
        table.add_row(
            layer["name"],
            layer["kind"],
            str(layer["in_features"]),
            str(layer["out_features"]),
            f"{layer['parameters']:,}",
            "yes" if layer["keyed"] else "",
        )
    out.print(table)


def _bundle_table(info: dict):
    from rich.table import Table

    model = ", ".join(f"{k} {v}" for k, v in info["model"].items())
    n = info.get("records", info.get("users"))
    who = plural(n, "record") if "records" in info else plural(n, "enrolled user")
    table = Table(title=f"{info['bundle']}: {info['mode']} bundle, format {info['format_version']}",
                  title_justify="left", show_header=False)  # fmt: skip
    table.add_column()
    table.add_column(overflow="fold")  # the keyed layers wrap at their commas, a long name folds
    a = info["audit"]
    audit = "none recorded (prop attack --record)" if a is None else _audit(a)
    layers = ", ".join(x["name"] for x in info["keyed_layers"])
    rows = [
        ("version", f"{info['bundle_version']} of bundle {info['bundle_id']}" if info["bundle_id"]
                    else "none (format 1-4: an older copy is not detected)"),  # fmt: skip
        ("model", f"{model}; task {info['task']}"),
        ("key", f"{info['key_bits']} bits; {who}"),
        ("keyed layers", f"{len(info['keyed_layers'])}: {layers}"),
        ("payload", ", ".join(f"{k} {v}" for k, v in info["payload"].items()) if "payload" in info else "-"),
        ("files", f"{info['files']}, every sha256 checked"),  # a missing one is an error (describe)
        ("audit", audit),
        ("signature", info["signature"] or "none"),
        ("onnx export", _export(info["onnx_export"], info["bundle"])),
    ]
    for k, v in rows:
        table.add_row(k, v)
    return table


def _audit(a: dict) -> str:
    """The recorded audit as a line: its probes, and its --max-leak decision, a pass only where every
    default probe ran (``passed``)."""
    missing = a["missing_probes"]
    if a["probes"] is None:
        probes = "probes not recorded"
    else:
        probes = "probes " + (", ".join(a["probes"]) or "none")
        if missing:
            probes += f" (not the default audit: {', '.join(missing)} did not run)"
    leak = a["max_leak"]
    if not leak:
        decision = "no --max-leak"
    elif not leak["passed"]:
        decision = f"--max-leak {leak['threshold']}: FAILED " + ", ".join(leak["failing"] or [])
    elif a["passed"]:
        decision = f"--max-leak {leak['threshold']}: passed"
    else:
        decision = f"--max-leak {leak['threshold']}: NOT A PASS (passed on the probes above only)"
    return f"recorded {a['recorded_utc']} by prop {a['prop_version']}; {probes}; {decision}"


def _export(e: dict | None, bundle: str) -> str:
    """The export's state as a line: whether it matches the bundle as it is, and what it binds."""
    if e is None:
        return "no"
    if not e["current"]:
        return f"STALE, in {e['folder']}: {e['why']}; {e['fix'].replace('BUNDLE', bundle)}"
    held = f"{plural(e['records'], 'user record')}, " if "records" in e else ""
    return f"yes, in {e['folder']} ({held}{plural(e['bound_keys'], 'key')} bound)"
