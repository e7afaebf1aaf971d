"""Optimisers outside ``torch.optim``: TRPO's natural-gradient step with a KL line search, and the Hessian-vector
product strategies it takes (:mod:`umrl.optim.hvp`)."""
from umrl.optim.hvp import HessianVectorProduct, KLHessian
from umrl.optim.trpo import TRPOStep, conjugate_gradient

__all__ = ["HessianVectorProduct", "KLHessian", "TRPOStep", "conjugate_gradient"]
