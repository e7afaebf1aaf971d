"""scripts/diagnostics/velocity_definition.py: the reference's half_cheetah velocity, transcribed, is the torso
subtree's centre-of-mass velocity, and the script runs as docs/fidelity.md shows it (with smaller sizes)."""
import runpy
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "diagnostics" / "velocity_definition.py"

gymnasium = pytest.importorskip("gymnasium")
mujoco = pytest.importorskip("mujoco")


def test_reference_comvel_is_the_subtree_com_velocity():
    reference_comvel = runpy.run_path(str(SCRIPT))["reference_comvel"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        env = gymnasium.make("HalfCheetah-v5")
    env.reset(seed=0)
    model, rng = env.unwrapped.model, np.random.default_rng(0)
    data = mujoco.MjData(model)
    torso = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "torso")
    for _ in range(10):
        env.step(rng.uniform(-1.0, 1.0, size=model.nu))
        data.qpos[:], data.qvel[:] = env.unwrapped.data.qpos, env.unwrapped.data.qvel
        mujoco.mj_forward(model, data)
        mujoco.mj_subtreeVel(model, data)
        assert reference_comvel(model, data, torso) == pytest.approx(data.subtree_linvel[torso, 0], abs=1e-9)
    env.close()


def test_script_prints_both_velocities():
    out = subprocess.run([sys.executable, str(SCRIPT), "--episodes", "2", "--steps", "5", "--seed", "0"],
                         capture_output=True, text=True, timeout=120, check=True).stdout
    assert "umrl x_velocity" in out and "reference comvel" in out and "mean |difference|" in out
