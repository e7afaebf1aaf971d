"""The Gaussian policy starts as maml_rl's MLPs do: Xavier-uniform weights, zero biases, std ``init_std``."""
import math

import torch
from tensordict import TensorDict
from torch import nn

from umrl.modules.policy import make_gaussian_policy, policy_log_std


def test_xavier_uniform_weights_and_zero_biases():
    torch.manual_seed(0)
    policy = make_gaussian_policy(5, 3, hidden=(300, 300), init_std=0.5)
    layers = [m for m in policy.modules() if isinstance(m, nn.Linear)]
    assert [tuple(layer.weight.shape) for layer in layers] == [(300, 5), (300, 300), (3, 300)]
    for layer in layers:
        fan_out, fan_in = layer.weight.shape
        bound = math.sqrt(6.0 / (fan_in + fan_out))
        assert torch.count_nonzero(layer.bias) == 0
        assert layer.weight.abs().max() <= bound
        # a uniform draw on [-bound, bound] has variance bound^2 / 3 (PyTorch's default init is far narrower here)
        torch.testing.assert_close(layer.weight.var(), torch.tensor(bound**2 / 3), rtol=0.1, atol=0.0)
    torch.testing.assert_close(policy_log_std(policy).detach(), torch.full((3,), math.log(0.5)))


def test_zero_observation_gives_zero_mean():
    policy = make_gaussian_policy(4, 2, hidden=(8,))
    out = policy(TensorDict({"observation": torch.zeros(6, 4)}, [6]))
    assert torch.count_nonzero(out["loc"]) == 0
