"""umrl.absent_modules.mark_absent_modules: absent packages answer at once, installed ones are left alone."""
import importlib.machinery
import importlib.util
import subprocess
import sys

import pytest
import torch
from tensordict import TensorDict

from umrl.absent_modules import mark_absent_modules

MISSING = "umrl_test_no_such_package"


@pytest.fixture
def clean_modules():
    yield
    sys.modules.pop(MISSING, None)


def test_an_absent_package_is_marked_once_and_still_fails_to_import(clean_modules):
    assert importlib.util.find_spec(MISSING) is None
    assert mark_absent_modules((MISSING, "numpy")) == (MISSING,)  # numpy is installed: left alone
    assert sys.modules[MISSING] is None and importlib.util.find_spec(MISSING) is None
    with pytest.raises(ModuleNotFoundError):
        __import__(MISSING)
    assert mark_absent_modules((MISSING,)) == ()
    import numpy  # noqa: F401  (still importable)


def test_tensordict_module_outputs_no_longer_search_the_path(monkeypatch):
    """The hot path the marker exists for: ``TensorDict.from_any`` on a tensor (every TensorDictModule output)
    asks whether pandas is installed; after marking, that must not search ``sys.path`` (whether or not pandas is
    installed here: if it is, the first call imports it and later ones find it in ``sys.modules``)."""
    mark_absent_modules()
    TensorDict.from_any(torch.zeros(3))
    searches = []
    original = importlib.machinery.PathFinder.find_spec
    monkeypatch.setattr(importlib.machinery.PathFinder, "find_spec",
                        classmethod(lambda cls, name, *a, **k: searches.append(name) or original(name, *a, **k)))
    for _ in range(5):
        TensorDict.from_any(torch.zeros(3))
    assert searches == []


def test_process_tuning_marks_absent_packages():
    """Every process umrl's command lines own gets the marker (recipes, suite workers, benchmarks) through
    :func:`umrl.process.tune_process`; importing umrl alone does not (tests/test_process.py)."""
    probe = ("import importlib.util, sys; installed = importlib.util.find_spec('pandas') is not None; "
             "from umrl.process import tune_process; tune_process(keep_freed_memory=False); "
             "print(installed or sys.modules.get('pandas', 'unmarked') is None)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "True"
