"""Training on several processes started by Hugging Face Accelerate (`accelerate launch`), data parallel.

Every process holds the whole model and draws the same step (the same seed, so the same rows and keys);
each runs the forward and backward of its own share of the step's rows, and the gradients are summed
over the processes (``torch.distributed.all_reduce`` on the process group Accelerate set up: gloo on
CPU, NCCL on GPUs). The loss is written as a sum over rows, each weighted by its share of its term of
Eq. 8, so the summed gradient is the single-process gradient of the same step: one process and N
processes train the same model, up to the order of floating-point sums (tests/train/test_distributed.py
states the tolerance). Only the first process writes the bundle.

Started without `accelerate launch` (no ``WORLD_SIZE`` above 1), nothing here imports accelerate or
touches torch.distributed. Every recipe trains this way; a LeRobot policy's own random draws are made
per row (``row_noise``) and its loss split by ``PolicyProtocol.loss_parts``, so that holds for them too.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch

from prop_cli.errors import PropError

DIST_EXTRA = "pip install 'prop-keys[dist]'"


@dataclass(frozen=True)
class Ranks:
    """This process's place among the processes training together (one process: rank 0 of 1)."""

    rank: int = 0
    world: int = 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def share(self, n: int) -> torch.Tensor:
        """Indices of this process's rows among a step's ``n`` rows (contiguous, sizes differing by one)."""
        return torch.tensor_split(torch.arange(n), self.world)[self.rank]

    def check_rows(self, rows: dict[str, int]) -> None:
        """Every process needs a row of each term of a step (``rows``: the flag that sets a term's rows
        per step -> their number)."""
        for flag, n in rows.items():
            if n < self.world:
                raise PropError(
                    f"{flag} {n}: fewer rows per step than the {self.world} processes sharing each step",
                    f"raise {flag} to at least {self.world}, or start fewer processes",
                )

    def finish(self) -> None:
        """Wait for every process (the first one writes the bundle), then leave the process group: a
        process that exits while another still works makes gloo abort it."""
        if self.world > 1:
            import torch.distributed as dist

            if dist.is_initialized():
                dist.barrier()
                dist.destroy_process_group()

    def sum_tensor(self, t: torch.Tensor) -> torch.Tensor:
        """``t`` summed over the processes (a copy)."""
        import torch.distributed as dist

        t = t.clone()
        dist.all_reduce(t)
        return t

    def sum_gradients(self, params: list[torch.Tensor]) -> None:
        """Sum every parameter's gradient over the processes, in one flat buffer (one collective). A
        parameter no process computed a gradient for keeps none (Adam then skips it, as in one process)."""
        import torch.distributed as dist

        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
        had = torch.tensor([p.grad is not None for p in params], dtype=grads[0].dtype, device=grads[0].device)
        flat = torch.cat([*(g.reshape(-1) for g in grads), had])
        dist.all_reduce(flat)
        offset = 0
        for p, g in zip(params, grads):
            n = g.numel()
            p.grad = flat[offset : offset + n].view_as(g)
            offset += n
        for p, h in zip(params, flat[offset:].tolist()):
            if h == 0:
                p.grad = None

    def weight(self, local: torch.Tensor) -> torch.Tensor:
        """Each loss part's share on this process: its rows' weights ``local`` (parts,) over the
        weights of all the processes' rows (``PolicyProtocol.loss_parts``); 1 on one process."""
        if self.world == 1:
            return torch.ones_like(local)
        return local / self.sum_tensor(local).clamp_min(1e-12)


# `accelerate launch` options that shard the model, which prop does not do (docs/cli.md says what blocks
# FSDP): refused rather than ignored, since whoever asks for them counts on the memory they save.
SHARDED = {"ACCELERATE_USE_FSDP": "--use_fsdp", "ACCELERATE_USE_DEEPSPEED": "--use_deepspeed"}


def ranks_from_env(device: str = "cpu") -> Ranks:
    """The processes `accelerate launch` started (``WORLD_SIZE``); one process when it did not."""
    for var, flag in SHARDED.items():
        if os.environ.get(var, "false").lower() == "true":
            raise PropError(
                f"accelerate launch {flag}: prop trains data parallel, every process holding the whole "
                "model; it does not shard it",
                f"launch without {flag} (docs/cli.md, Several processes)",
            )
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world <= 1:
        return Ranks()
    try:
        from accelerate import PartialState
    except ImportError:
        raise PropError(
            f"WORLD_SIZE={world}: training on several processes needs Hugging Face Accelerate", DIST_EXTRA
        ) from None
    import torch.distributed as dist

    # cpu=True: gloo on the CPU (`accelerate launch --multi_gpu --num_processes N` on a machine without
    # GPUs; `--cpu` alone starts one process).
    state = PartialState(cpu=not str(device).startswith("cuda"))
    # Count the processes that really joined: a collective every one of them takes part in.
    joined = torch.ones(1)
    dist.all_reduce(joined)
    if int(joined.item()) != state.num_processes:
        raise PropError(
            f"{int(joined.item())} of {state.num_processes} processes joined the process group",
            "start them with accelerate launch --multi_gpu --num_processes N",
        )
    return Ranks(state.process_index, state.num_processes)
