"""The suite's yaml and the meta-test dataclasses hold one default per key: a value set in both agrees."""
import dataclasses

import pytest
from omegaconf import OmegaConf
from script_loading import REPO

from umrl.metatest import AdaptationConfig, CellSpec, SweepConfig


def _defaults(cls) -> dict:
    return {f.name: f.default for f in dataclasses.fields(cls) if f.default is not dataclasses.MISSING}


def _plain(value):
    return tuple(value) if isinstance(value, (list, tuple)) else value


@pytest.mark.parametrize("group, cls", [("protocol", AdaptationConfig), ("sweep", SweepConfig), (None, CellSpec)])
def test_suite_yaml_agrees_with_the_dataclass_defaults(group, cls):
    suite = OmegaConf.to_container(OmegaConf.load(REPO / "umrl/suite/config/suite.yaml"))
    values = suite[group] if group else suite
    shared = sorted(set(values) & set(_defaults(cls)))
    assert shared, f"no key of {cls.__name__} in the suite's yaml"
    differing = {k: (values[k], _defaults(cls)[k]) for k in shared if _plain(values[k]) != _plain(_defaults(cls)[k])}
    assert not differing, f"yaml value vs {cls.__name__} default: {differing}"
