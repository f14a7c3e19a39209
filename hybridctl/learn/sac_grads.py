"""SAC's gradients: each loss computed, checked finite and differentiated into the parameters' ``.grad``.

:class:`EagerGrads` by autograd through the networks; :class:`CompiledGrads` (``SACConfig.compile``)
with each loss's forward and backward one ``torch.compile``-d ``torch.func.grad_and_value`` graph.
Both take the agent (a :class:`hybridctl.learn.sac.SAC`, or SSAC) and call its ``critic_loss`` and
``actor_loss``; the optimizer steps next.
"""

from __future__ import annotations

import torch
from torch.func import grad_and_value

from ..systems.compiled import LazyCompiled
from .optim import set_grads as _set_grads

__all__ = ["EagerGrads", "CompiledGrads"]


class EagerGrads:
    """SAC's gradients by autograd through the networks: each call computes a loss, checks it is
    finite and leaves its gradients in the parameters' ``.grad`` (the optimizer steps next)."""

    def __init__(self, agent):
        self.agent = agent

    def critic(self, obs, act, rew, next_obs, done, eps, alpha) -> torch.Tensor:
        """The twin-Q loss (:meth:`hybridctl.learn.sac.SAC.critic_loss`) and its gradients in the critics' ``.grad``."""
        agent = self.agent
        loss = agent.critic_loss(None, obs, act, rew, next_obs, done, eps, alpha)
        agent._check_finite("q_loss", loss)
        agent.q_opt.zero_grad(set_to_none=True)
        loss.backward()
        return loss

    def actor(self, obs, eps, alpha) -> tuple[torch.Tensor, torch.Tensor]:
        """The policy loss and log densities (:meth:`hybridctl.learn.sac.SAC.actor_loss`), its gradients in the actor's ``.grad``."""
        agent = self.agent
        loss, logp = agent.actor_loss(None, None, obs, eps, alpha)
        agent._check_finite("pi_loss", loss)
        agent.actor_opt.zero_grad(set_to_none=True)
        loss.backward()
        return loss, logp


class CompiledGrads(EagerGrads):
    """:class:`EagerGrads` with each loss's forward and backward one ``torch.compile``-d
    ``torch.func.grad_and_value`` graph (the same loss functions, called with the parameters as
    tensors). Measured here against the alternatives (2-core EPYC, one thread, 4 x 32 networks,
    minibatch 128, gradient steps/s): eager autograd 374, these graphs 1,137, ``torch.compile`` of
    the losses' forward with autograd's backward 489, the whole step with compiled autograd 189."""

    def __init__(self, agent, strict: bool):
        super().__init__(agent)
        critic_grad, actor_grad = grad_and_value(agent.critic_loss), grad_and_value(agent.actor_loss, has_aux=True)

        # one function each: torch.compile keeps its graphs per code object, and grad_and_value's
        # wrappers share one, so both losses compiled through it would re-check each other's guards
        def critic_grads(*args):
            return critic_grad(*args)

        def actor_grads(*args):
            return actor_grad(*args)
        self.critic_grads = LazyCompiled(critic_grads, True, strict, "SAC's critic loss")
        self.actor_grads = LazyCompiled(actor_grads, True, strict, "SAC's actor loss")
        self.refresh()

    def refresh(self) -> None:
        """List the parameters and their detached views once (they share storage, so they follow every
        in-place update: optimizers, ``load_state_dict``); called again when a run starts."""
        agent = self.agent
        self.q_params = agent._q_params
        self.actor_params = list(agent.actor.parameters())
        self.detached_actor = {k: v.detach() for k, v in agent.actor.named_parameters()}
        self.detached_critics = agent._q_param_dicts()

    def critic(self, obs, act, rew, next_obs, done, eps, alpha) -> torch.Tensor:
        grads, loss = self.critic_grads(self.detached_critics, obs, act, rew, next_obs, done, eps, alpha)
        self.agent._check_finite("q_loss", loss)
        _set_grads(self.q_params, [g for per_critic in grads for g in per_critic.values()])
        return loss

    def actor(self, obs, eps, alpha) -> tuple[torch.Tensor, torch.Tensor]:
        grads, (loss, logp) = self.actor_grads(self.detached_actor, self.detached_critics, obs, eps, alpha)
        self.agent._check_finite("pi_loss", loss)
        _set_grads(self.actor_params, list(grads.values()))
        return loss, logp
