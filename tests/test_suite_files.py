"""The files a suite keeps beside its runs (its wandb group, its timings): an empty or garbage one is named and
started afresh, never a crash before the work or a lost report after it."""
import json

import pytest
from omegaconf import OmegaConf

from umrl.suite.run import read_suite_file, suite_group


@pytest.mark.parametrize("text", ["", "{not json", "[1, 2]", '{"group": 3}', "\udcff"])
def test_a_broken_suite_state_gets_a_new_group_with_a_warning(tmp_path, text):
    (tmp_path / "suite_state.json").write_text(text, errors="surrogateescape")
    cfg = OmegaConf.create({"logger": {"group": None}, "output_dir": str(tmp_path), "profile_name": "p"})
    with pytest.warns(UserWarning, match="suite_state.json is not the dict the suite wrote"):
        group = suite_group(cfg)
    assert group.startswith("suite-p-")
    assert json.loads((tmp_path / "suite_state.json").read_text()) == {"group": group}
    assert suite_group(cfg) == group  # kept from then on


def test_timings_are_read_as_written_or_started_afresh(tmp_path):
    path = tmp_path / "timings.json"
    assert read_suite_file(path, list) is None
    path.write_text(json.dumps([{"wall": 1.0, "jobs": {}}]))
    assert read_suite_file(path, list) == [{"wall": 1.0, "jobs": {}}]
    path.write_text("garbage")
    with pytest.warns(UserWarning, match="timings.json is not the list the suite wrote"):
        assert read_suite_file(path, list) is None
