"""The demo: the paper's imitation-learning task, end to end through the `prop` command line.

    bash scripts/demo.sh            # set up and run this (about a minute on 2 cores)
    python -m examples.demo [--keep DIR]

1. Write the example: a base MLP behaviour-cloned from an expert that moves a robot towards its goal
   (saved as safetensors), the user's demonstrations (the negated action), and test states.
2. `prop keygen`, `prop inspect`, `prop personalize` (defaults), `prop run` with and without the key;
   a key one bit off is enrolled in nothing, so `prop run` refuses it, and runs the bundle's base with
   `--allow-unenrolled-key` (what the rows "key 1 bit off" show).
3. Print base vs personalized behaviour on a few states, and the errors on 2000 held-out states.
4. The same with a sealed bundle (`--seal`: the base is the original, the user's part is encrypted),
   where a wrong key runs the original exactly.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from examples.il_task import write_example


def prop(*args: object, refused: bool = False) -> None:
    """Run `prop ARGS`; ``refused``: the command must fail with a usage error (exit 2)."""
    cmd = [sys.executable, "-m", "prop_cli.cli.main", *map(str, args)]
    print("$ prop " + " ".join(map(str, args)), flush=True)
    rc = subprocess.run(cmd, check=not refused).returncode
    if refused and rc != 2:
        raise SystemExit(f"expected prop {args[0]} to refuse (exit 2), got exit {rc}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--keep", type=Path, help="write the files here and keep them")
    args = ap.parse_args(argv)
    work = args.keep or Path(tempfile.mkdtemp(prefix="prop-demo-"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:
        print("writing the IL example (training the base policy, ~10 s)...", flush=True)
        paths = write_example(work / "il", seed=0)
        key, bundle = work / "k.bin", work / "mine.prop"
        test = np.load(paths["test"])
        np.save(work / "x.npy", test["x"])
        prop("keygen", key, "--force")
        prop("inspect", paths["base"])
        prop(
            "personalize",
            paths["base"],
            "--data",
            paths["mine"],
            "--general-data",
            paths["general"],
            "--key-file",
            key,
            "--out",
            bundle,
            "--force",
        )
        wrong = bytearray(key.read_bytes())
        wrong[0] ^= 1  # the user's key with one bit flipped
        (work / "k_wrong.bin").write_bytes(bytes(wrong))
        (work / "k_wrong.bin").chmod(0o600)
        # A key enrolled in nothing is refused (the bundle may have been replaced); to measure it, as
        # here, --allow-unenrolled-key runs the bundle's base for it.
        prop("run", bundle, "--input", work / "x.npy", "--key-file", work / "k_wrong.bin", "--output",
             work / "y_refused.npy", "--force", refused=True)  # fmt: skip
        wrong = ["--key-file", work / "k_wrong.bin", "--allow-unenrolled-key"]
        for name, key_args in (("key", ["--key-file", key]), ("nokey", []), ("wrong", wrong)):
            prop("run", bundle, "--input", work / "x.npy", *key_args, "--output", work / f"y_{name}.npy",
                 "--force")  # fmt: skip

        y, yp = test["y"], test["y_personal"]
        outs = {name: np.load(work / f"y_{name}.npy") for name in ("key", "nokey", "wrong")}
        print(
            "\nstate (robot x, y, goal x, y)    expert action   personal action | with key"
            "         no key           1 bit off"
        )
        for i in range(5):
            s = ", ".join(f"{v:5.1f}" for v in test["x"][i])
            row = [y[i], yp[i], outs["key"][i], outs["nokey"][i], outs["wrong"][i]]
            print(f"({s})  " + "  ".join("(" + ", ".join(f"{v:+.2f}" for v in a) + ")" for a in row))

        def mse(a, b):
            return float(((a - b) ** 2).mean())

        print(f"\nmse on {len(y)} held-out states       vs expert (original)   vs personal (negated)")
        for name, label in (("key", "with the user's key"), ("nokey", "no key"), ("wrong", "key 1 bit off")):
            print(f"  {label:30s} {mse(outs[name], y):10.4f}            {mse(outs[name], yp):10.4f}")

        sealed = work / "sealed.prop"
        print("\nthe same user, sealed (private against whoever holds the bundle's files):", flush=True)
        prop("personalize", paths["base"], "--data", paths["mine"], "--key-file", key, "--out", sealed,
             "--seal", "--force")  # fmt: skip
        for name, key_args in (("key", ["--key-file", key]), ("nokey", []), ("wrong", wrong)):
            prop("run", sealed, "--input", work / "x.npy", *key_args, "--output", work / f"s_{name}.npy",
                 "--force")  # fmt: skip
        souts = {name: np.load(work / f"s_{name}.npy") for name in ("key", "nokey", "wrong")}
        print(f"\nsealed bundle, mse on {len(y)} states   vs expert (original)   vs personal (negated)")
        for name, label in (("key", "with the user's key"), ("nokey", "no key"), ("wrong", "key 1 bit off")):
            print(f"  {label:30s} {mse(souts[name], y):10.4f}            {mse(souts[name], yp):10.4f}")
        same = np.array_equal(souts["wrong"], souts["nokey"])
        print(f"  key 1 bit off gives exactly the no-key (original) outputs: {'yes' if same else 'NO'}")
        print(
            f"\ndone in {time.perf_counter() - t0:.0f} s; files in {work}"
            + ("" if args.keep else " (removed)")
        )
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
