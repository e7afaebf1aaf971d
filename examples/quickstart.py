"""Quick start: DIAYN skills on point_nav -> MAML meta-trained on them (UML-DIAYN) -> meta-test on held-out goals,
beside learning from scratch (the baseline).

    python examples/quickstart.py [output_dir]      # ~20 s of CPU time; default outputs/quickstart/<start time>

A run claims its own folders: a second run into the same output_dir is refused (docs/safety.md), so the default
is a new folder each time.

Everything runs on one torch thread, the recipes' ``num_threads``: the numbers are those of ``umrl diayn`` / ``umrl
maml`` with the same overrides (at torch's default count they drift apart, and the run was ~10x slower on 2 busy
cores: docs/quickstart.md).
"""
import sys
import time

import umrl.trainers
from umrl.metatest import AdaptationConfig, CellSpec, curves_from_rows, read_rows, run_cell
from umrl.process import torch_threads

METHODS = ("uml_diayn", "scratch")


def quickstart(out=None, *, diayn=(), maml=(), steps=3) -> dict[str, list[float]]:
    """Mean meta-test return of UML-DIAYN and of scratch after k = 0..steps updates, ``{method: [return at k]}``;
    ``diayn``/``maml``: extra overrides of the tiny profiles; ``out`` None: ``outputs/quickstart/<start time>``."""
    out = out or time.strftime("outputs/quickstart/%Y%m%d-%H%M%S")
    with torch_threads(1):  # opt-in, restored on exit: the configs' num_threads, as the command lines apply it
        umrl.trainers.train("diayn", ["+profile=diayn_tiny", f"output_dir={out}/diayn", "progress=false", *diayn])
        run = umrl.trainers.train("maml", ["+profile=maml_tiny", "proposal=diayn", f"diayn_checkpoint={out}/diayn",
                                           f"output_dir={out}/maml", "progress=false", *maml])
        protocol = AdaptationConfig(num_steps=steps, num_trajectories=10)
        cells = [CellSpec(method=method, env="point_nav", seed=0, checkpoint=checkpoint, num_tasks=5, protocol=protocol,
                          output=f"{out}/meta_test_{method}.csv")
                 for method, checkpoint in zip(METHODS, (run["checkpoint"], None))]
        curves = curves_from_rows(read_rows([run_cell(cell) for cell in cells]))["point_nav"]
    return {method: curves[method].mean.tolist() for method in METHODS}


if __name__ == "__main__":
    returns = quickstart(*sys.argv[1:2])
    print("mean return on 5 held-out goals after k policy-gradient steps (toy budgets: the pipeline, not a result)")
    for k, (uml, scratch) in enumerate(zip(returns["uml_diayn"], returns["scratch"])):
        print(f"  k = {k}: UML-DIAYN {uml:7.1f}   scratch {scratch:7.1f}")
