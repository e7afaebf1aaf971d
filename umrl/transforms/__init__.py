"""Transforms that define umrl's rewards: skills, the discriminator's pseudo-reward, VIME's bonus, task rewards.

``TaskReward`` lives in :mod:`umrl.envs.task_reward` (it is part of each env's task family) and is re-exported here.
"""
from umrl.envs.task_reward import TaskReward
from umrl.transforms.discriminator_reward import DiscriminatorReward
from umrl.transforms.skill import SkillTransform
from umrl.transforms.vime_bonus import VIMEBonus

__all__ = ["DiscriminatorReward", "SkillTransform", "TaskReward", "VIMEBonus"]
