"""The compared methods as data: :data:`METHODS` (name -> :class:`Method`: the :class:`Pretraining` run that produces
its initialisation and its update rule at meta-test), :func:`get_method` and :func:`default_lr_schedule`.

A module of its own so that the result tables (:mod:`umrl.metatest.results`) can name a method's default schedule
without importing the cells that run it (:mod:`umrl.metatest.methods`, which writes those tables).
"""
from __future__ import annotations

from dataclasses import dataclass

from umrl.metatest.protocol import DEFAULT_SGD_SCHEDULE
from umrl.proposals import PROPOSALS

#: Pre-training recipes (the MAML recipe's task proposals are :data:`umrl.proposals.PROPOSALS`).
RECIPES = ("diayn", "maml", "vime")


@dataclass(frozen=True)
class Pretraining:
    """One pre-training run kind: ``recipe`` (``diayn`` | ``maml`` | ``vime``) and, for MAML, its ``proposal``.

    ``kind`` is its name in paths and job keys (``"diayn"``, ``"maml_random"``, ...); ``requires`` lists the runs
    it reads (MAML with the DIAYN proposal reads the DIAYN run of the same env and seed).
    """

    recipe: str
    proposal: str | None = None

    def __post_init__(self):
        if self.recipe not in RECIPES:
            raise ValueError(f"pretraining recipe must be one of {list(RECIPES)}, got {self.recipe!r}.")
        if (self.recipe == "maml") != (self.proposal is not None) or (
                self.proposal is not None and self.proposal not in PROPOSALS):
            raise ValueError(f"pretraining proposal: the maml recipe needs one of {list(PROPOSALS)} and the others "
                             f"none; got recipe {self.recipe!r} with proposal {self.proposal!r}.")

    @property
    def kind(self) -> str:
        return self.recipe if self.proposal is None else f"{self.recipe}_{self.proposal}"

    @property
    def requires(self) -> tuple[Pretraining, ...]:
        return (Pretraining("diayn"),) if self.proposal == "diayn" else ()


@dataclass(frozen=True)
class Method:
    """A compared method: its pre-training (None: scratch) and its meta-test update rule (``sgd`` | ``adam``)."""

    name: str
    pretraining: Pretraining | None
    optimizer: str


METHODS: dict[str, Method] = {m.name: m for m in (
    Method("uml_diayn", Pretraining("maml", "diayn"), "sgd"),
    Method("uml_random", Pretraining("maml", "random"), "sgd"),
    Method("oracle", Pretraining("maml", "oracle"), "sgd"),
    Method("vime_init", Pretraining("vime"), "adam"),
    Method("diayn_init", Pretraining("diayn"), "adam"),
    Method("scratch", None, "adam"),
    # "UML-random (bounded arena, ablation)": not the paper's method and in no profile's default methods; it tests
    # why UML-random fails on point_nav (meta-training positions clipped to [-1, 1]², meta-test env unbounded).
    Method("uml_random_arena", Pretraining("maml", "random_arena"), "sgd"),
)}


def default_lr_schedule(method: str) -> str:
    """The step-size schedule a method's cells run without a ``protocol.sgd_schedule`` override:
    :data:`~umrl.metatest.protocol.DEFAULT_SGD_SCHEDULE` for the SGD methods (MAML initialisations), ``"constant"``
    for Adam's and for names that are not methods."""
    method_record = METHODS.get(method)
    return DEFAULT_SGD_SCHEDULE if method_record is not None and method_record.optimizer == "sgd" else "constant"


def get_method(name: str) -> Method:
    """The :class:`Method` called ``name``; a clear error for an unknown one."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid choices: {list(METHODS)}.")
    return METHODS[name]


__all__ = ["METHODS", "RECIPES", "Method", "Pretraining", "default_lr_schedule", "get_method"]
