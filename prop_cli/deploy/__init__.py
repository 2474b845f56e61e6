"""Shipping a bundle: publishing to the Hugging Face hub (``publish``, `prop push`), signing and verifying
(``sign``, `prop verify`) and a sealed payload as a peft adapter (``peft``, `prop export --peft`). Running
a bundle (torch, ONNX, `prop eval`'s rollouts) is ``prop_cli.run``'s."""
