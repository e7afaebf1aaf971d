"""Importing umrl and calling its library functions changes nothing process-wide; umrl.process tunes on request."""
import subprocess
import sys
import textwrap

PROBE = textwrap.dedent("""
    import ctypes, sys
    import torch
    torch.set_num_threads(3)
    looked_up = []
    real_cdll = ctypes.CDLL

    class Spy:  # records which C functions are looked up (mallopt is glibc's heap tuning)
        def __init__(self, *args, **kwargs):
            self.lib = real_cdll(*args, **kwargs)

        def __getattr__(self, name):
            looked_up.append(name)
            return getattr(self.lib, name)

    ctypes.CDLL = Spy
    before = {name for name, module in sys.modules.items() if module is None}
    BODY
    marked = {name for name, module in sys.modules.items() if module is None} - before
    print(torch.get_num_threads(), sorted(marked), "mallopt" in looked_up)
""")

LIBRARY_CALLS = """
import umrl, umrl.objectives, umrl.metatest, umrl.launch
from umrl.trainers import MAMLTrainer
from umrl.trainers.config import compose
cfg = compose("maml", ["proposal=random", "env.horizon=5", "meta_batch_size=2", "trajectories_per_task=2",
                       "policy.hidden=[8]", "iterations=1", "num_threads=1", "logger.backend=none", "progress=false",
                       "output_dir=" + sys.argv[1]])
trainer = MAMLTrainer(cfg)
trainer.train()
trainer.close()
"""


def _probe(body: str, tmp_path) -> list[str]:
    script = PROBE.replace("BODY", body.strip())
    result = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True, check=False,
                            timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout.strip().splitlines()[-1].split(" ", 1)


def test_importing_umrl_and_training_leave_the_process_alone(tmp_path):
    threads, rest = _probe(LIBRARY_CALLS, tmp_path)
    assert threads == "3"  # not the config's num_threads=1
    assert rest == "[] False"  # no module marked absent, glibc's malloc untouched


def test_tune_process_applies_the_settings_it_documents(tmp_path):
    body = "from umrl.process import tune_process\napplied = tune_process(num_threads=2)"
    threads, rest = _probe(body, tmp_path)
    assert threads == "2"
    assert rest.endswith("True")  # mallopt looked up (whether glibc applied it depends on the environment)
