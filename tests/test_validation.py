"""umrl.validation: each check accepts what it documents and names the argument, the bad value and what is accepted."""
import functools
import math

import numpy as np
import pytest
import torch

from umrl.validation import (
    InvalidType,
    InvalidValue,
    check_bool,
    check_choice,
    check_finite,
    check_float,
    check_int,
    check_list,
    check_mapping,
    check_not_diverged,
    check_path_exists,
    check_positive,
    check_probability,
    check_str,
    resolve_device,
)


def test_check_int():
    assert check_int("horizon", 5, min=1) == 5
    assert type(check_int("n", np.int64(3), min=0)) is int
    with pytest.raises(InvalidType, match=r"^horizon: got 2\.5; expected an integer >= 1$"):
        check_int("horizon", 2.5, min=1)
    with pytest.raises(InvalidType, match=r"^flag: got True; expected an integer$"):
        check_int("flag", True)
    with pytest.raises(InvalidValue, match=r"^k: got 7; expected an integer in \[0, 5\]$"):
        check_int("k", 7, min=0, max=5)


def test_check_float_bounds_and_finiteness():
    assert check_float("lr", 1) == 1.0 and isinstance(check_float("lr", 1), float)
    with pytest.raises(InvalidValue, match=r"^inner_lr: got nan; expected a finite number > 0$"):
        check_positive("inner_lr", math.nan)
    with pytest.raises(InvalidValue, match=r"^x: got inf; expected a finite number$"):
        check_float("x", math.inf)
    with pytest.raises(InvalidValue, match=r"^f: got 0; expected a finite number in \(0, 1\]$"):
        check_float("f", 0, gt=0, le=1)
    with pytest.raises(InvalidType, match=r"^lr: got '1e-3'; expected a finite number > 0$"):
        check_positive("lr", "1e-3")


def test_check_probability():
    assert check_probability("gamma", 1) == 1.0 and check_probability("gamma", 0.0) == 0.0
    with pytest.raises(InvalidValue, match=r"^gamma: got 1\.5; expected a finite number in \[0, 1\]$"):
        check_probability("gamma", 1.5)


def test_divergence_guard_names_every_non_finite_entry():
    check_not_diverged({"loss_a": torch.tensor(1.0), "step": 3}, "ok")
    bad = {"loss_a": torch.tensor(1.0), "loss_b": torch.tensor(float("nan")), "loss_c": torch.tensor([0.0, -math.inf])}
    with pytest.raises(FloatingPointError, match=r"^non-finite \['loss_b', 'loss_c'\] in update 3: lower the learning"):
        check_not_diverged(bad, "update 3")


def test_check_finite_tensor_names_first_bad_entry():
    tasks = torch.zeros(4, 2)
    assert check_finite("tasks", tasks) is tasks
    tasks[2, 1] = math.nan
    tasks[3, 0] = math.inf
    with pytest.raises(InvalidValue, match=r"^tasks: got a tensor of shape \[4, 2\] and dtype torch.float32 "
                                           r"\(2 non-finite, first at index \(2, 1\): nan\); expected finite values"):
        check_finite("tasks", tasks)
    with pytest.raises(InvalidValue, match="^alpha: got nan"):
        check_finite("alpha", math.nan)


def test_check_bool_str_choice_mapping():
    assert check_bool("resume", False) is False
    with pytest.raises(InvalidType, match=r"^resume: got 1; expected true or false$"):
        check_bool("resume", 1)
    with pytest.raises(InvalidValue, match=r"^name: got ''; expected a non-empty string$"):
        check_str("name", "")
    assert check_choice("backend", "csv", ("wandb", "csv")) == "csv"
    with pytest.raises(InvalidValue, match=r"^backend: got 'tb'; expected one of 'wandb', 'csv'$"):
        check_choice("backend", "tb", ("wandb", "csv"))
    with pytest.raises(InvalidValue, match=r"^backend: got \['csv'\]; expected one of"):
        check_choice("backend", ["csv"], {"wandb": 0, "csv": 1})
    assert check_mapping("overrides", {"a": 1}) == {"a": 1}
    with pytest.raises(InvalidType, match=r"^overrides: got \[1\]; expected a mapping with string keys$"):
        check_mapping("overrides", [1])


def test_check_list_reports_the_bad_entry():
    item = functools.partial(check_int, min=0)
    assert check_list("seeds", (0, 1), item, min_len=1) == [0, 1]
    with pytest.raises(InvalidValue, match=r"^seeds: got \[\]; expected a non-empty list of integers$"):
        check_list("seeds", [], item, min_len=1, what="integers")
    with pytest.raises(InvalidValue, match=r"^seeds\[1\]: got -1; expected an integer >= 0$"):
        check_list("seeds", [0, -1], item)
    with pytest.raises(InvalidValue, match=r"\(repeated entries\); expected a list of distinct"):
        check_list("seeds", [0, 0], item, unique=True)
    with pytest.raises(InvalidType, match=r"^seeds: got '01'"):
        check_list("seeds", "01", item)


def test_check_path_exists(tmp_path):
    assert check_path_exists("reuse", str(tmp_path)) == str(tmp_path)
    missing = tmp_path / "nope"
    with pytest.raises(InvalidValue, match=rf"^reuse: got '{missing}' \({missing} does not exist\); "
                                           r"expected an existing file or directory$"):
        check_path_exists("reuse", str(missing))


def test_resolve_device():
    assert resolve_device("device", "cpu") == "cpu"
    assert resolve_device("device", "auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(InvalidValue, match=r"^device: got 'gpu'; expected one of 'cpu', 'cuda', 'auto'$"):
        resolve_device("device", "gpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal of cuda on a machine without a GPU")
def test_resolve_device_refuses_cuda_without_gpu():
    with pytest.raises(InvalidValue, match=r"^device: got 'cuda' \(no CUDA device is available on this machine\); "
                                           r"expected one of 'cpu', 'auto'$"):
        resolve_device("device", "cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_resolve_device_accepts_cuda_with_gpu():
    assert resolve_device("device", "cuda") == "cuda"
