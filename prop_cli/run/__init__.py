"""Running a bundle, in one place: in torch (``policy``: ``KeyedPolicy``, ``run_bundle``, ``run_policy``),
on a file of inputs (``inputs``, ``file``: `prop run`), as ONNX graphs (``onnx``: `prop export --onnx`,
`prop run --onnx`) and in closed loop (``rollout`` with ``envs``: `prop eval`). The bundle's files are
``prop_cli.bundle``'s (the format); this package turns them and a key into behaviour."""

from .policy import KeyedPolicy, WrongKeyWarning, run_bundle, run_policy

__all__ = ["KeyedPolicy", "WrongKeyWarning", "run_bundle", "run_policy"]
