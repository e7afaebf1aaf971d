"""Public imports like TorchRL's (``from umrl.objectives import MAMLLoss``) and no import running up the layers."""
import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

UMRL = Path(__file__).resolve().parents[1] / "umrl"

PUBLIC = {
    "umrl.objectives": {"DIAYNLoss", "DIAYNUpdate", "MAMLLoss", "VIMELoss", "compute_advantages", "vpg_loss", "trajectory_mask"},
    "umrl.transforms": {"SkillTransform", "DiscriminatorReward", "VIMEBonus", "TaskReward"},
    "umrl.modules": {"make_gaussian_policy", "make_discriminator", "BayesianDynamics"},
    "umrl.optim": {"TRPOStep"},
    "umrl.envs": {"make_env", "make_task_env", "EnvSpec", "register_env", "get_env_spec", "ENV_NAMES"},
    "umrl.checkpoints": {"load_maml_policy", "load_skill_policy", "load_vime_policy", "save_maml_checkpoint"},
}

#: Lower layers never import higher ones (equal layers may import each other). Networks (modules) import no other
#: umrl package: they sit beside the envs, below the transforms that hold them (VIMEBonus, DiscriminatorReward).
LAYERS = {
    "rng": 0, "resume_state": 0, "loggers": 0, "figures": 0, "plain_config": 0, "atomic_write": 0, "validation": 0,
    "trajectories": 0, "profiling": 0, "launch": 0, "heap": 0, "absent_modules": 0, "process": 0, "seed_replay": 0,
    "folder_lock": 0, "signals": 0,
    "envs": 1, "modules": 1, "theory": 1, "transforms": 2, "rollout": 4, "objectives": 5, "optim": 5,
    "proposals": 6, "skill_coverage": 6, "reward_map": 6, "checkpoints": 6, "metatest": 7, "configs": 7, "run_folders": 7,
    "trainers": 8, "suite": 9, "cli": 10, "__main__": 11,
}


@pytest.mark.parametrize("package", sorted(PUBLIC))
def test_subpackages_export_their_public_names(package):
    module = importlib.import_module(package)
    assert PUBLIC[package] <= set(module.__all__)
    assert all(hasattr(module, name) for name in module.__all__)


def _umrl_imports(path: Path) -> set[str]:
    """Top-level umrl packages/modules imported anywhere in ``path`` (function-level imports included)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
        names += [a.name for a in node.names] if isinstance(node, ast.Import) else []
        found |= {n.split(".")[1] for n in names if n.startswith("umrl.")}
    return found


def test_no_import_runs_up_the_layers():
    upward = set()
    for path in UMRL.rglob("*.py"):
        parts = path.relative_to(UMRL).with_suffix("").parts
        if parts == ("__init__",):
            continue
        layer = parts[0]
        assert layer in LAYERS, f"{path}: add {layer!r} to LAYERS"
        upward |= {(layer, target) for target in _umrl_imports(path) if LAYERS[target] > LAYERS[layer]}
    assert not upward, f"upward imports (layer, imported): {sorted(upward)}"


def test_no_package_imports_itself_through_another():
    """The package-level import graph has no cycle (equal layers may import each other, but never both ways)."""
    graph = {}
    for path in UMRL.rglob("*.py"):
        parts = path.relative_to(UMRL).with_suffix("").parts
        if parts != ("__init__",):
            graph.setdefault(parts[0], set()).update(_umrl_imports(path) - {parts[0]})

    def reaches(start, goal, seen):
        return any(nxt == goal or (nxt not in seen and reaches(nxt, goal, seen | {nxt})) for nxt in graph.get(start, ()))

    assert not [name for name in graph if reaches(name, name, {name})]


def test_every_module_imports_first_in_a_fresh_process():
    """An import cycle shows only when its module is imported first (``umrl.rollout`` before ``umrl.objectives``
    once failed): import each module with no umrl module loaded, in one child process (torch stays loaded)."""
    names = sorted(".".join(("umrl", *p.relative_to(UMRL).with_suffix("").parts)).removesuffix(".__init__")
                   for p in UMRL.rglob("*.py"))
    code = (
        "import importlib, sys, torch, torchrl\n"
        f"for name in {names!r}:\n"
        "    for loaded in [m for m in sys.modules if m == 'umrl' or m.startswith('umrl.')]:\n"
        "        del sys.modules[loaded]\n"
        "    try:\n"
        "        importlib.import_module(name)\n"
        "    except ImportError as err:\n"
        "        sys.exit(f'{name}: {err}')\n"
    )
    result = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]


def test_version_comes_from_the_installed_metadata():
    import importlib.metadata

    import umrl

    assert umrl.__version__ == importlib.metadata.version("umrl")
