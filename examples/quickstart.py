"""Quick start: DIAYN skills on point_nav -> MAML meta-trained on them (UML-DIAYN) -> meta-test on held-out goals.

    python examples/quickstart.py [output_dir]      # ~35 s of CPU time; default outputs/quickstart
"""
import sys

import recipes
from umrl.metatest import AdaptationConfig, CellSpec, curves_from_rows, read_rows, run_cell


def quickstart(out="outputs/quickstart", *, diayn=(), maml=(), steps=3) -> list[float]:
    """Mean meta-test return after k = 0..steps updates; ``diayn``/``maml``: extra overrides of the tiny profiles."""
    recipes.train("diayn", ["+profile=diayn_tiny", f"output_dir={out}/diayn", "progress=false", *diayn])
    run = recipes.train("maml", ["+profile=maml_tiny", "proposal=diayn", f"diayn_checkpoint={out}/diayn",
                                 f"output_dir={out}/maml", "progress=false", *maml])
    cell = CellSpec(method="uml_diayn", env="point_nav", seed=0, checkpoint=run["checkpoint"], num_tasks=5,
                    protocol=AdaptationConfig(num_steps=steps, num_trajectories=10), output=f"{out}/meta_test.csv")
    return curves_from_rows(read_rows([run_cell(cell)]))["point_nav"]["uml_diayn"].mean.tolist()


if __name__ == "__main__":
    returns = quickstart(*sys.argv[1:2])
    print("UML-DIAYN meta-test return at k = 0, 1, ...:", ", ".join(f"{r:.1f}" for r in returns))
