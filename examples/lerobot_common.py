"""What the LeRobot closed-loop examples share (examples/metaworld, examples/pointmass_diffusion): the small
Diffusion policy's lerobot-train flags, prop personalize's Eq. 8 batch, and the trained checkpoint as
LeRobot loads it in prop's closed-loop controller. Importing it changes nothing in the process (no
environment variables: examples.metaworld's task sets HF_HUB_OFFLINE, this module does not)."""

from __future__ import annotations

from pathlib import Path

# lerobot-train: the small Diffusion policy's observation history, chunk and sampler (10 DDPM steps of
# 100), no random crop and group norm in its image encoder (so prop's two terms share one U-Net call).
DIFFUSION = [
    "--policy.n_obs_steps=2",
    "--policy.horizon=16",
    "--policy.n_action_steps=8",
    "--policy.num_inference_steps=10",
    "--policy.crop_shape=null",
    "--policy.use_group_norm=true",
]
# prop personalize: the Eq. 8 batch of the LeRobot examples (every row runs the image encoder); each
# example adds its own --steps.
PERSONALIZE_BATCH = (
    "--user-rows 16 --null-rows 8 --neighbour-keys 4 --random-keys 4 --samples-per-key 1 --null-weight 2 "
    "--lr 1e-3 --base-lr-scale 0.1"
).split()


def original_controller(path: Path):
    """The trained checkpoint as LeRobot loads it (its class, its processors), in prop's closed-loop
    controller (LeRobot's select_action between the processors)."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    from prop_adapters.lerobot.policy import Controller

    cfg = PreTrainedConfig.from_pretrained(path)
    cfg.device = "cpu"
    policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg)
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(path))
    return Controller(policy, pre, post, {k: tuple(f.shape) for k, f in cfg.input_features.items()})


def lerobot_train_args(repo_id: str, root: Path, policy: list[str], output_dir: Path, job: str) -> list[str]:
    """``lerobot-train``'s arguments for a local dataset on the CPU, one checkpoint at the last step, no
    hub and no wandb, as both examples run it (``policy``: the policy's own flags, ``--steps=N`` in them)."""
    steps = int(next(a for a in policy if a.startswith("--steps=")).split("=")[1])
    return [f"--dataset.repo_id={repo_id}", f"--dataset.root={root}", *policy,
            "--policy.device=cpu", "--policy.push_to_hub=false", "--num_workers=0",
            f"--save_freq={steps}", "--log_freq=100", "--wandb.enable=false",
            f"--output_dir={output_dir}", f"--job_name={job}", "--seed=0"]  # fmt: skip
