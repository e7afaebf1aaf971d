"""Optimisers outside ``torch.optim``: TRPO's natural-gradient step with a KL line search, the Hessian-vector
product strategies it takes (:mod:`umrl.optim.hvp`) and MAML's products through the inner step
(:mod:`umrl.optim.meta_hvp`)."""
from umrl.optim.hvp import HessianVectorProduct, KLHessian
from umrl.optim.meta_hvp import META_HVPS, AnalyticHVP, ExactHVP, GaussNewtonHVP, MetaHVP, make_meta_hvp
from umrl.optim.trpo import TRPOStep, conjugate_gradient

__all__ = ["META_HVPS", "AnalyticHVP", "ExactHVP", "GaussNewtonHVP", "HessianVectorProduct", "KLHessian", "MetaHVP",
           "TRPOStep", "conjugate_gradient", "make_meta_hvp"]
