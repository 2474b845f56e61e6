"""Shipping a bundle: ONNX export and runtime (``onnx``), closed-loop evaluation in an environment
(``rollout``, `prop eval`) and publishing to the Hugging Face hub (``publish``, `prop push`)."""
