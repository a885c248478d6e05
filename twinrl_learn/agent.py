"""The off-policy actor-critic that fine-tunes a Stage I policy with RL.

- **Actor**: the SFT policy itself (its tanh-Gaussian head), trained with TwinRL's
  ConRFT-style objective ``L = beta * L_IL + eta * L_Q``: ``L_IL`` is the policy's
  imitation loss on demo and intervention rows (augmented as in SFT),
  ``L_Q = -Q(s, a ~ pi)`` normalised by the batch's mean |Q| (as TD3+BC does) so that
  beta and eta weigh comparable terms;
  optional entropy ``alpha * log pi`` with a learned temperature (SAC).
- **Critic**: an ensemble of LayerNorm MLPs on :meth:`Policy.critic_inputs` (frozen
  image features or the privileged state, proprio, instruction) and the whole action
  chunk (Q-chunking: the critic scores the chunk the policy executes), TD targets from
  the minimum of the target ensemble, soft target updates.
- **Offline phase** (before online data): a Cal-QL regulariser pushes Q down on
  sampled actions and up on the data's, with the policy's Q clipped from below by the
  data's Monte-Carlo return so it stays calibrated for the online switch.

An update runs an image policy's encoders once on the batch's observations and once on
its next observations (:meth:`Policy.keypoints`) and shares the keypoints between all
its terms; only the imitation term's shifted images are encoded anew.

The agent runs where its policy's weights are (:meth:`Policy.from_pretrained`'s
``device``): critics and temperature go there, and on a GPU the losses' forward passes
run under bfloat16 autocast (:mod:`twinrl_learn.compute`). Its random generator stays
on the CPU, so a seed draws the same batches and noise on every device.

Three settings (``RLConfig.method``) give the methods compared in TwinRL:
``twinrl`` / ``conrft`` (the objective above, offline Cal-QL then online) and
``hil-serl`` (SAC with entropy and no imitation term; its offline phase warms the
critic only, and the actor steps every ``critic_per_actor`` updates).
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import asdict
from pathlib import Path

import torch
from torch import nn

from twinrl_data.atomic import write_text_atomic
from twinrl_learn.compute import mixed_precision
from twinrl_learn.errors import LearnError
from twinrl_learn.policy import Policy
from twinrl_learn.replay import TransitionBatch
from twinrl_learn.settings import RLConfig
from twinrl_learn.training_state import load_state, save_state


class CriticEnsemble(nn.Module):
    """``critics`` independent LayerNorm MLPs Q(s, a_chunk); output (E, B)."""

    def __init__(self, input_dim: int, action_dim: int, members: int, hidden: int) -> None:
        super().__init__()
        self.members = nn.ModuleList(
            nn.Sequential(
                nn.Linear(input_dim + action_dim, hidden),
                nn.LayerNorm(hidden),
                nn.ReLU(),
                nn.Linear(hidden, hidden),
                nn.LayerNorm(hidden),
                nn.ReLU(),
                nn.Linear(hidden, 1),
            )
            for _ in range(members)
        )

    def forward(self, inputs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        x = torch.cat([inputs, actions.flatten(1)], dim=-1)
        # float32 values: TD errors in bfloat16 (under a GPU's autocast) would be coarse.
        return torch.stack([m(x).squeeze(-1) for m in self.members]).float()


class Agent:
    """Actor (a :class:`Policy`), critic ensemble, targets, optimizers and counters, on
    the policy's device."""

    def __init__(self, policy: Policy, config: RLConfig) -> None:
        self.policy = policy
        self.config = config
        self.device = policy.device
        torch.manual_seed(config.seed)
        c = policy.config
        self.critic = CriticEnsemble(
            policy.critic_input_dim, c.chunk * c.action_dim, config.critics, config.hidden
        ).to(self.device)
        self.target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = torch.tensor(
            math.log(config.temperature_init), device=self.device, requires_grad=True
        )
        self.actor_opt = torch.optim.Adam(policy.parameters(), lr=config.actor_lr)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=config.critic_lr)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=config.actor_lr)
        self.updates = 0
        self.env_steps = 0
        self.generator = torch.Generator().manual_seed(config.seed)

    # ------------------------------------------------------------------ helpers
    @property
    def alpha(self) -> torch.Tensor:
        if self.config.entropy:
            return self.log_alpha.exp().detach()
        return torch.zeros((), device=self.device)

    def online(self) -> bool:
        return self.updates >= self.config.offline_steps

    def weights(self) -> tuple[float, float]:
        """(beta, eta) for the current phase."""
        beta = self.config.beta
        if self.online() and self.config.beta_online is not None:
            beta = self.config.beta_online
        return beta, self.config.eta

    def actor_moves(self) -> bool:
        """Whether this update steps the actor: not while the critic warms up, then once
        every ``critic_per_actor`` updates."""
        c = self.config
        return (
            self.updates >= c.critic_warmup
            and (self.updates - c.critic_warmup) % (c.critic_per_actor) == 0
        )

    def actor_reads_q(self) -> bool:
        """Whether the actor's loss has the Q term (and so needs the critic's view)."""
        return self.weights()[1] > 0 or self.config.entropy

    def _tensors(self, batch: TransitionBatch) -> dict[str, torch.Tensor | dict | None]:
        """The batch as normalised tensors, with the image encoders' keypoints of its
        observations (None for the state policy) computed once for every loss: with a
        gradient where the actor's Q term trains the encoders through them."""
        p = self.policy
        obs = p.inputs(
            batch.state, batch.environment_state, batch.images, batch.instruction, batch.estimates
        )
        following = p.inputs(
            batch.next_state,
            batch.next_environment_state,
            batch.next_images,
            batch.instruction,
            batch.next_estimates,
        )
        with torch.set_grad_enabled(self.actor_reads_q()):
            keypoints = p.keypoints(obs)
        with torch.no_grad():
            next_keypoints = p.keypoints(following)
        return {
            "obs": obs,
            "next": following,
            "keypoints": keypoints,
            "next_keypoints": next_keypoints,
            "actions": self._on_device(
                p.normalize("action", torch.from_numpy(batch.actions))
            ).clamp(-1, 1),
            "reward": self._on_device(torch.from_numpy(batch.reward)),
            "discount": self._on_device(torch.from_numpy(batch.discount)),
            "mc_return": self._on_device(torch.from_numpy(batch.mc_return)),
        }

    def _on_device(self, tensor: torch.Tensor) -> torch.Tensor:
        return tensor.to(self.device, non_blocking=True)

    # ------------------------------------------------------------------ losses
    def critic_loss(self, t: dict, online: bool) -> tuple[torch.Tensor, dict[str, float]]:
        p = self.policy
        inputs = p.critic_inputs(t["obs"], t["keypoints"])
        with torch.no_grad():
            next_inputs = p.critic_inputs(t["next"], t["next_keypoints"])
            next_features = p.features(t["next"], t["next_keypoints"])
            next_actions, next_log_prob = p.rsample(t["next"], next_features)
            next_q = self.target(next_inputs, next_actions).min(0).values
            next_q = next_q - self.alpha * next_log_prob
            target = t["reward"] + t["discount"] * next_q
        q = self.critic(inputs, t["actions"])
        td = ((q - target) ** 2).mean()
        metrics = {"q": q.mean().item(), "td": td.item()}
        loss = td
        if not online and self.config.cql_alpha > 0:
            regulariser = self._cal_ql(inputs, t, q)
            loss = loss + self.config.cql_alpha * regulariser
            metrics["cql"] = regulariser.item()
        return loss, metrics

    def _cal_ql(self, inputs: torch.Tensor, t: dict, q_data: torch.Tensor) -> torch.Tensor:
        """Cal-QL: logsumexp of Q over uniform and policy actions (the policy's Q
        clipped from below by the Monte-Carlo return) minus Q of the data's actions."""
        n, (b, h, a) = self.config.cql_actions, t["actions"].shape
        repeated = inputs.repeat(n, 1)
        uniform = self._on_device(torch.rand((n * b, h, a), generator=self.generator) * 2 - 1)
        with torch.no_grad():  # n draws per observation from its features
            features = self.policy.features(t["obs"], t["keypoints"]).repeat(n, 1)
            policy_actions, _ = self.policy.rsample(t["obs"], features)
        q_uniform = self.critic(repeated, uniform).view(-1, n, b)
        q_policy = self.critic(repeated, policy_actions).view(-1, n, b)
        q_policy = torch.maximum(q_policy, t["mc_return"][None, None])
        stacked = torch.cat([q_uniform, q_policy], dim=1)
        return (torch.logsumexp(stacked, dim=1) - q_data).mean()

    def actor_loss(self, t: dict, demo_rows: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
        """beta * L_IL(demo rows) + eta * L_Q (+ alpha * log pi with entropy)."""
        beta, eta = self.weights()
        p = self.policy
        loss = torch.zeros((), device=self.device)
        metrics: dict[str, float] = {}
        if self.actor_reads_q():
            actions, log_prob = p.rsample(t["obs"], p.features(t["obs"], t["keypoints"]))
            q = self.critic(p.critic_inputs(t["obs"], t["keypoints"]), actions).min(0).values
            scale = q.abs().mean().detach().clamp_min(1e-3)
            l_q = -(q / scale).mean()
            loss = loss + eta * l_q + (self.alpha * log_prob).mean() / scale
            metrics |= {"l_q": l_q.item(), "log_pi": log_prob.mean().item()}
            if self.config.entropy:
                target = self.config.target_entropy_per_dim * actions[0].numel()
                alpha_loss = -(self.log_alpha * (log_prob.detach() + target)).mean()
                self.alpha_opt.zero_grad(set_to_none=True)
                alpha_loss.backward()
                self.alpha_opt.step()
                metrics["alpha"] = self.alpha.item()
        if beta > 0 and bool(demo_rows.any()):
            # The same augmentation as SFT; without it OOD wore down (docs/results/defaults.md).
            demo = p.augment({k: v[demo_rows] for k, v in t["obs"].items()}, self.generator)
            l_il = p.imitation_loss(demo, t["actions"][demo_rows])
            loss = loss + beta * l_il
            metrics["l_il"] = l_il.item()
        return loss, metrics

    # ------------------------------------------------------------------ update
    def update(self, batch: TransitionBatch) -> dict[str, float]:
        """One gradient step of critic and actor on ``batch`` (the imitation term uses
        its ``demo`` rows: demonstrations and interventions)."""
        online = self.online()
        self.policy.train()
        with mixed_precision(self.device):
            t = self._tensors(batch)
            critic_loss, metrics = self.critic_loss(t, online)
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        nn.utils.clip_grad_norm_(self.critic.parameters(), 10.0)
        self.critic_opt.step()
        actor_metrics: dict[str, float] = {}
        if self.actor_moves():
            with mixed_precision(self.device):
                demo_rows = self._on_device(torch.from_numpy(batch.demo))
                actor_loss, actor_metrics = self.actor_loss(t, demo_rows)
            if actor_loss.requires_grad:
                self.actor_opt.zero_grad(set_to_none=True)
                actor_loss.backward()
                nn.utils.clip_grad_norm_(self.policy.parameters(), 10.0)
                self.actor_opt.step()
        with torch.no_grad():
            for target, source in zip(
                self.target.parameters(), self.critic.parameters(), strict=True
            ):
                target.lerp_(source, self.config.tau)
        self.policy.eval()
        self.updates += 1
        return metrics | actor_metrics | {"online": float(online)}

    # -------------------------------------------------------------- checkpoints
    def adopt_critic(self, folder: str | Path) -> bool:
        """Take the critic and its target from the RL checkpoint in ``folder`` (Stage
        II's agent, to go on judging with what it learnt in the twin), when it is one;
        optimizers and counters start afresh. Returns whether there was one."""
        path = Path(folder) / "agent.pt"
        if not path.is_file():
            return False
        state = load_state(path)
        try:
            self.critic.load_state_dict(state["critic"])
            self.target.load_state_dict(state["target"])
        except RuntimeError as error:
            raise LearnError(
                f"the critic in {folder} does not fit {self.config.critics} critics of width "
                f"{self.config.hidden} on this policy's inputs; use the settings it was "
                "trained with, or a new critic"
            ) from error
        return True

    def state_dict(self) -> dict:
        return {
            "policy": self.policy.state_dict(),
            "critic": self.critic.state_dict(),
            "target": self.target.state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            "updates": self.updates,
            "env_steps": self.env_steps,
            "generator": self.generator.get_state(),
            "torch_rng": torch.get_rng_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.policy.load_state_dict(state["policy"])
        self.critic.load_state_dict(state["critic"])
        self.target.load_state_dict(state["target"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.alpha_opt.load_state_dict(state["alpha_opt"])
        self.updates, self.env_steps = state["updates"], state["env_steps"]
        self.generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])

    def save(self, folder: str | Path) -> Path:
        """The policy as a normal checkpoint (``Policy.from_pretrained`` reads it) plus
        ``agent.pt`` (critics, optimizers, counters, RNG) and ``rl_config.json``."""
        folder = Path(folder)
        self.policy.save_pretrained(folder)
        save_state(self.state_dict(), folder / "agent.pt")
        write_text_atomic(folder / "rl_config.json", json.dumps(asdict(self.config), indent=1))
        return folder

    @classmethod
    def load(cls, folder: str | Path, device: str | torch.device = "cpu") -> Agent:
        """The RL checkpoint in ``folder``, on ``device`` (wherever it was trained)."""
        folder = Path(folder)
        if not (folder / "agent.pt").is_file():
            raise LearnError(f"{folder} holds no agent.pt; it is not an RL checkpoint")
        agent = cls(Policy.from_pretrained(folder, device), RLConfig.load(folder))
        agent.load_state_dict(load_state(folder / "agent.pt"))
        return agent
