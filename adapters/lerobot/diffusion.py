"""LeRobot Diffusion Policy through the policy protocol: its denoiser (``UNet``, a ``policy.Denoiser``).

- **Deployed chunk**: the sampler's output over the whole horizon (B, horizon, action_dim), normalised.
  Its noise is what LeRobot draws for that frame alone after ``torch.manual_seed(noise_seed)``: the
  prior and every DDPM/DDIM step come from one generator per row, all seeded with ``noise_seed``
  (diffusers takes a list of generators, one per row). So a frame's chunk does not depend on the batch
  it runs in, the same frame under two keys is sampled from the same noise, and a batch of one equals
  LeRobot's own ``select_action`` after ``torch.manual_seed(noise_seed)``. The horizon starts at the
  oldest observation of the row's history: in closed loop ``select_action`` acts
  ``chunk[n_obs_steps - 1 : n_obs_steps - 1 + n_action_steps]``, so its first action is
  ``chunk[n_obs_steps - 1]``, not ``chunk[0]``.
- **User term**: the policy's own loss (noise-prediction MSE at a random timestep), unchanged.
- **Fallback term**: in eval mode the denoiser is deterministic given (observation, x_t, t). Each
  fallback frame gets ``FALLBACK_DRAWS`` rows, each with t uniform over the training timesteps (with
  ``--fallback-times sampler``: over the ``num_inference_steps`` timesteps the sampler visits) and
  noise eps, x_t = the scheduler's ``add_noise`` of the original's deployed chunk for that frame (with
  ``--fallback-times trajectory``: x_t = the original's own sampler state at that step, its sampler run
  on the frame from the row's own noise, ``UNet.states``: where the closed loop runs the keyed U-Net); the
  keyed policy's prediction is distilled towards the frozen original's on the same (observation, x_t,
  t), MSE (its own loss's distance). No key, random keys and Hamming neighbours alike. The draws are
  made before training (``fallback_noise``) and each row's original prediction is computed once, when a
  step first draws it, and kept, as ACT's chunks are: computing the original on every step's rows cost
  a third of the step (bench_lerobot_step). Both terms share one U-Net call
  (``joint_terms``) where training and eval mode compute the same (no random crop or batch norm in an
  image encoder): a PRoP step then costs 1.13x LeRobot's own step at the example's size, against 1.55x
  with two calls.
- **Keyed layers** by default: every Conv1d of the U-Net and its FiLM projections (``cond_encoder``),
  the down/mid/up blocks and the final convolution: 97% of the U-Net's parameters at LeRobot's
  default size (down_dims 512/1024/2048), 98% of the small ones in examples/ (``prop inspect``).
  Not keyed: the timestep encoder, the image encoder (key them with ``--layers``) and the upsampling
  ConvTranspose1d (transposed convolutions are not keyable).
"""

from __future__ import annotations

import copy

import torch

from .policy import ACTION, PAD, Denoiser, LeRobotProtocol

DIFFUSION_LAYERS = [r"diffusion\.unet\.(down_modules|mid_modules|up_modules|final_conv)\..+"]
OBS_IMAGES = "observation.images"


class UNet(Denoiser):
    """Diffusion's denoiser (its conditional U-Net under LeRobot's DDPM/DDIM scheduler): ``owner`` is the
    policy's protocol (see the module docstring)."""

    def __init__(self, owner: DiffusionProtocol) -> None:
        self.owner = owner

    def _observations(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """What DiffusionModel's conditioning takes: the features (B, n_obs, ...), cameras stacked."""
        b = {k: batch[k] for k in self.owner.input_features}
        if self.owner.config.image_features:
            b[OBS_IMAGES] = torch.stack([b[k] for k in self.owner.config.image_features], dim=-4)
        return b

    def chunk(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.owner.policy.eval()
        model, c = self.owner.model, self.owner.config
        cond = model._prepare_global_conditioning(self._observations(batch))
        rows = cond.shape[0]
        gens = [torch.Generator(cond.device).manual_seed(self.owner.noise_seed) for _ in range(rows)]
        shape = (1, c.horizon, c.action_feature.shape[0])
        noise = torch.cat([torch.randn(shape, generator=g, device=g.device, dtype=cond.dtype) for g in gens])
        return model.conditional_sample(rows, global_cond=cond, generator=gens, noise=noise)

    def sampler_timesteps(self) -> torch.Tensor:
        """The timesteps LeRobot's sampler visits (its scheduler at ``num_inference_steps``)."""
        model = self.owner.model
        scheduler = copy.deepcopy(model.noise_scheduler)  # set_timesteps changes the scheduler's state
        scheduler.set_timesteps(model.num_inference_steps)
        return scheduler.timesteps.long().cpu()

    def draws(self, rows: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        c = self.owner.config  # the timestep, then the noise, for every row
        follows = self.owner.fallback_times == "trajectory"
        if self.owner.fallback_times == "sampler" or follows:  # only the timesteps the closed loop runs
            visited = self.sampler_timesteps()
            k = torch.randint(0, len(visited), (rows,), generator=generator)
            t = visited[k]
        else:
            t = torch.randint(0, self.owner.model.noise_scheduler.config.num_train_timesteps, (rows,),
                              generator=generator)  # fmt: skip
        eps = torch.randn((rows, c.horizon, c.action_feature.shape[0]), generator=generator)
        drawn = {"t": t, "eps": eps}
        if follows:  # the sampler's step k (its t) from the prior eps, its step noise seeded per row
            drawn |= {"k": k, "seed": torch.randint(0, 2**62, (rows,), generator=generator)}
        return drawn

    def noised(self, x0: torch.Tensor, draws: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        t = draws["t"].to(x0.device)
        if "k" in draws:  # --fallback-times trajectory: x0 is already the sampler's state at t (``states``)
            return {"x_t": x0, "t": t}
        return {"x_t": self.owner.model.noise_scheduler.add_noise(x0, draws["eps"].to(x0), t), "t": t}

    follows_sampler = True

    def states(self, batch: dict[str, torch.Tensor], draws: dict[str, torch.Tensor]) -> torch.Tensor:
        """Each row's state in LeRobot's own sampler (``conditional_sample``) before its step ``k``: the
        sampler run on the row's observation from the prior ``eps``, the step noise from a generator per
        row seeded with ``seed``, stopped at step k (k = 0: the prior). A row's state does not depend on
        the batch it runs in."""
        self.owner.policy.eval()
        model = self.owner.model
        cond = model._prepare_global_conditioning(self._observations(batch))
        k = draws["k"].to(cond.device)
        x = draws["eps"].to(cond)
        gens = [torch.Generator(cond.device).manual_seed(int(s)) for s in draws["seed"]]
        scheduler = copy.deepcopy(model.noise_scheduler)  # set_timesteps changes the scheduler's state
        scheduler.set_timesteps(model.num_inference_steps)
        out = x.clone()
        for i, t in enumerate(scheduler.timesteps[: int(k.max())]):
            at = torch.full((len(x),), int(t), dtype=torch.long, device=x.device)
            x = scheduler.step(model.unet(x, at, global_cond=cond), t, x, generator=gens).prev_sample
            out[k == i + 1] = x[k == i + 1]
        return out

    @property
    def joins_terms(self) -> bool:
        # The U-Net has no dropout; an image encoder differs between training and eval where it crops at
        # random or uses batch norm. Without those, one eval-mode forward computes both terms.
        c = self.owner.config
        return not c.image_features or (c.crop_shape is None and c.use_group_norm)

    def joint_terms(
        self, user: dict[str, torch.Tensor], fallback: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """LeRobot's ``compute_loss`` on the user rows (its draws of noise and timestep, in its order) and
        the denoiser on the fallback rows, as one U-Net call: a step of small models is bound by
        per-operator overhead, so one call of 2n rows costs about one of n."""
        self.owner.policy.eval()
        model, c = self.owner.model, self.owner.config
        n = len(user[ACTION])
        obs = {k: torch.cat([user[k], fallback[k]]) for k in self.owner.input_features}
        cond = model._prepare_global_conditioning(self._observations(obs))
        trajectory = user[ACTION]
        eps = torch.randn(trajectory.shape, device=trajectory.device)
        t = torch.randint(0, model.noise_scheduler.config.num_train_timesteps, (n,), device=trajectory.device)
        noisy = model.noise_scheduler.add_noise(trajectory, eps, t.long())
        out = model.unet(torch.cat([noisy, fallback["x_t"]]), torch.cat([t.long(), fallback["t"].long()]),
                         global_cond=cond)  # fmt: skip
        target = eps if c.prediction_type == "epsilon" else trajectory
        loss = torch.nn.functional.mse_loss(out[:n], target, reduction="none")
        if c.do_mask_loss_for_padding:
            loss = loss * (~user[PAD]).unsqueeze(-1)
        return loss.mean(), out[n:]

    def output(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.owner.policy.eval()
        model = self.owner.model
        cond = model._prepare_global_conditioning(self._observations(batch))
        return model.unet(batch["x_t"], batch["t"], global_cond=cond)

    def describe(self) -> dict:
        c = self.owner.config
        return {
            "horizon": c.horizon,
            "n_obs_steps": c.n_obs_steps,
            "n_action_steps": c.n_action_steps,
            "noise_scheduler": c.noise_scheduler_type,
            "inference_steps": self.owner.model.num_inference_steps,
            "prediction_type": c.prediction_type,
        }


class DiffusionProtocol(LeRobotProtocol):
    """Diffusion through the policy protocol (see the module docstring)."""

    default_layers = DIFFUSION_LAYERS
    label = "Diffusion"

    @property
    def model(self) -> torch.nn.Module:
        return self.policy.diffusion

    def make_denoiser(self) -> UNet:
        return UNet(self)


__all__ = ["DIFFUSION_LAYERS", "DiffusionProtocol"]
