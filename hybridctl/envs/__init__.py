"""Gymnasium environments for swing-up: one system (:class:`SwingupEnv`) or a torch batch.

Importing this module registers one gymnasium id per system spec,
``hybridctl/<Name>Swingup-v0`` (``AcrobotSwingup``, ``CartpoleSwingup``,
``DoubleCartpoleSwingup``, ``PendulumSwingup``). Episodes truncate themselves after
``episode_duration / decision_period`` decisions, so no TimeLimit wrapper is added.

>>> import gymnasium as gym, hybridctl.envs
>>> env = gym.make("hybridctl/AcrobotSwingup-v0")
>>> venv = hybridctl.envs.TorchVectorEnv("acrobot", num_envs=4096)
"""

import gymnasium as gym

from ..systems import known_systems
from ..systems.success import is_balanced
from .postprocess import DimensionReward
from .single import STATE_BOUND, SwingupEnv, env_id
from .switched import SwitchedVectorEnv
from .vector import TorchVectorEnv

__all__ = ["DimensionReward", "SwingupEnv", "TorchVectorEnv", "SwitchedVectorEnv", "is_balanced", "env_id", "STATE_BOUND"]

for _name in known_systems(strict=False):  # a bad $HYBRIDCTL_SYSTEMS is reported where a system is loaded
    if env_id(_name) not in gym.registry:
        gym.register(id=env_id(_name), entry_point="hybridctl.envs.single:SwingupEnv",
                     kwargs={"system": _name})
