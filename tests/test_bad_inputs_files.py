"""The probe's file kinds (scripts/diagnostics/bad_inputs.py): how many, how they run, how they are sorted."""
from collections import Counter

import pytest
from script_loading import load_script

probe = load_script("scripts/diagnostics/bad_inputs.py")


def test_the_file_kinds_hold_over_a_hundred_cases_of_every_kind():
    kinds = Counter(case.kind for case in probe.FILE_CASES)
    assert sum(kinds.values()) >= 100 and len(probe.FILE_CASES) == len({c.label for c in probe.FILE_CASES})
    assert set(kinds) == {"special files", "hostile trees", "hostile metadata", "damaged files", "full disks",
                          "long and odd names", "folder locks"}


@pytest.mark.parametrize("output", [
    "CheckpointError: cannot read checkpoint /r/step_5.pt (a FIFO): not a regular file; give ...",
    "CheckpointError: cannot read checkpoint /r/step_1.pt (a MAML checkpoint): meta.inner_lr = nan; expected ...",
    "OSError: cannot write checkpoint /r/step_1.pt.tmp: No space left on device; free space ...",
    ("FileNotFoundError: no checkpoint file at /r (looked for step_*.safetensors and step_*.pt in it and in "
     "/r/checkpoints)."),
])
def test_a_checkpoint_error_is_a_clear_refusal(output):
    assert probe.verdict("refuse", 1, "Traceback\n" + output)[0] == "clear"


def test_a_file_case_runs_forked_and_a_hanging_one_is_stopped_at_the_time_limit(tmp_path):
    tree = next(c for c in probe.FILE_CASES if c.label.startswith("load_maml_policy(<a JSON tree nested"))
    hang = probe.file_case("special files", "a case that hangs", "import time; time.sleep(60)")
    results = {case.label: result for case, result in probe.run_forked([tree, hang], str(tmp_path), 5, 2)}
    code, output, _ = results[tree.label]
    assert probe.verdict(tree.expect, code, output)[0] == "clear" and "RecursionError" in output
    code, _, seconds = results[hang.label]
    assert code is None and seconds < 30
