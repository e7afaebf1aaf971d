"""``python -m umrl.checkpoints.export_skills SOURCE DESTINATION``: keep a DIAYN run's trained skills without its
replay buffer (:func:`umrl.checkpoints.export_diayn_skills`), e.g. to commit or share them."""
from __future__ import annotations

import argparse

from umrl.checkpoints.diayn import export_diayn_skills


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m umrl.checkpoints.export_skills", description=__doc__)
    parser.add_argument("source", help="a DIAYN seed's checkpoint: a step_*.safetensors (or .pt) file, a checkpoints/ "
                        "folder, a seed's folder (<output_dir>/seed<s>) or the output_dir of a run of one seed")
    parser.add_argument("destination", help="the new run directory (its checkpoints/ folder receives the copy)")
    args = parser.parse_args(argv)
    print(export_diayn_skills(args.source, args.destination))


if __name__ == "__main__":
    main()
