"""Optimisers outside ``torch.optim``: TRPO's natural-gradient step with a KL line search."""
from umrl.optim.trpo import TRPOStep, conjugate_gradient

__all__ = ["TRPOStep", "conjugate_gradient"]
