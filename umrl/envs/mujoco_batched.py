"""Batched MuJoCo CMPs: ``B`` copies of gymnasium's own v5 models, stepped as one TorchRL env.

:class:`BatchedMujocoEnv` reproduces gymnasium's ``HalfCheetah-v5`` / ``Ant-v5`` semantics exactly (same XML files,
frame skip, reset noise, reward terms, info values, Ant's healthy termination and clipped contact forces) without
gymnasium in the step loop. Each copy is advanced by the same calls gymnasium makes (``mj_step(nstep=frame_skip)``,
plus ``mj_rnePostConstraint`` where contact forces are observed), so trajectories match gymnasium's bit for bit.

A copy is its full integration state (``mjSTATE_INTEGRATION``: time, qpos, qvel, act, warm start, controls, applied
forces; ~100-150 floats), one row of the ``[B, nstate]`` state array of a :class:`mujoco.batch.Batch` (MuJoCo's own
batch: one native call steps all rows on a C++ thread pool with the GIL released, bit-identical to a loop of
``mj_step`` at any thread count). HalfCheetah is stepped by that call. Ant also needs ``mj_rnePostConstraint``
after each step (gymnasium's contact forces), which the batch does not run: its rows are stepped copy by copy on a
Python thread pool, one ``MjData`` per thread (``mj_step`` releases the GIL, the per-copy calls around it do not).
An acceleration sensor (``framelinacc``), which makes ``mj_step`` compute the contact forces, is no substitute: Ant
uses RK4, so gymnasium's post-step call sees the last Runge-Kutta stage while a sensor sees the step's first
(measured on 64 copies over 100 steps: identical states, raw contact forces up to 338 apart).

Keys (``B`` = batch size, all float32 unless noted): ``"observation"`` ``[B, obs_dim]``, ``"action"`` ``[B, act_dim]``
in ``[-1, 1]``, ``("next", "reward")`` ``[B, 1]`` zeros (reward-free CMP), ``"env_reward"`` ``[B, 1]`` gymnasium's
reward (0 at reset), the physics keys of the env's registry record (0 at reset for velocities and reward terms), and
``"done"``/``"terminated"``/``"truncated"`` ``[B, 1]`` bool. No time limit: wrap with ``StepCounter``.

Resume: the reset-noise generator is the env's only random state; ``set_seed`` seeds it, :attr:`rng_state` reads
and writes it, and it travels in ``state_dict()`` / ``load_state_dict()`` (``nn.Module`` extra state). The episodes
in progress (every copy's integration state and what the next step reads of the last one) are
:meth:`~BatchedMujocoEnv.episode_state` / :meth:`~BatchedMujocoEnv.load_episode_state`: a copy restored from them steps
on bit for bit as the saved one would.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import gymnasium
import mujoco
import mujoco.batch
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from umrl.envs.mujoco_log import disable_mujoco_log_file
from umrl.envs.registry import get_env_spec

disable_mujoco_log_file()  # MuJoCo warnings go to the console, not to ./MUJOCO_LOG.TXT

ASSETS_DIR = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets")

_STATE = int(mujoco.mjtState.mjSTATE_INTEGRATION)
_MIN_COPIES_PER_THREAD = 16


@dataclass(frozen=True)
class MujocoModelSpec:
    """What identifies one of our MuJoCo CMPs: its gymnasium id and kwargs, and the model file gymnasium loads."""

    gym_id: str
    xml_file: str
    frame_skip: int = 5
    reset_noise_scale: float = 0.1
    gym_kwargs: dict = field(default_factory=dict)


MODEL_SPECS: dict[str, MujocoModelSpec] = {
    "half_cheetah": MujocoModelSpec("HalfCheetah-v5", "half_cheetah.xml"),
    "ant": MujocoModelSpec("Ant-v5", "ant.xml"),
}

#: Ant's torso body: its subtree is the whole ant, so ``subtree_com[TORSO]`` is the ant's centre of mass.
TORSO = 1


def torso_com_xy(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """x-y of the centre of mass of the torso's subtree at ``data.qpos`` (a view into ``data.subtree_com``).

    The MAML reference code's ``get_body_com("torso")`` (``com_subtree`` after ``model.forward()``, i.e. at the
    post-step positions). Only position-dependent quantities are recomputed (``mj_kinematics``, ``mj_comPos``);
    ``data``'s other fields, and the integration state, are left as they are.
    """
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    return data.subtree_com[TORSO, :2]


def _state_slice(model: mujoco.MjModel, component: mujoco.mjtState) -> slice:
    """Where ``component`` lies in a ``_STATE`` vector (components are laid out in the order of their bits)."""
    start = mujoco.mj_stateSize(model, _STATE & (int(component) - 1))
    return slice(start, start + mujoco.mj_stateSize(model, int(component)))


def physics_keys(name: str) -> dict[str, int]:
    """Width of each physics key env ``name`` writes at every step and reset (its registry record's)."""
    return dict(get_env_spec(name).physics_keys)


def physics_spec(name: str, num_envs: int, device: torch.device | str) -> Composite:
    """Specs of ``"env_reward"`` and the physics keys of env ``name`` (float32, ``[num_envs, width]``)."""
    widths = {"env_reward": 1, **physics_keys(name)}
    return Composite(
        {key: Unbounded((num_envs, w), dtype=torch.float32, device=device) for key, w in widths.items()},
        shape=(num_envs,),
        device=device,
    )


class BatchedMujocoEnv(EnvBase):
    """``B`` copies of a gymnasium v5 MuJoCo model stepped as one batch (base class; see the module docstring).

    Subclasses set :attr:`NAME` and implement :meth:`_observe` (the observation from the state buffers) and
    :meth:`_step_values` (env reward, physics keys and termination).

    Args:
        num_envs: batch size ``B`` (> 0).

    Keyword Args:
        seed: seeds the reset noise (numpy ``PCG64``, like gymnasium's ``np_random``); ``None`` draws fresh entropy.
        device: device of the returned tensors (physics runs on CPU threads; outputs move once per step).
        num_threads: threads stepping the copies; default: the CPUs this process may use, with at least
            16 copies per thread.
    """

    NAME: str = ""
    # Ant reads the torso body's position and the contact forces (computed by mj_rnePostConstraint after the step):
    # stepped copy by copy on Python threads; the others in one mujoco.batch call.
    _reads_body_and_contacts = False
    batch_locked = True

    def __init__(
        self,
        num_envs: int,
        *,
        seed: int | None = None,
        device: torch.device | str = "cpu",
        num_threads: int | None = None,
    ):
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}.")
        if num_threads is not None and (isinstance(num_threads, bool) or not isinstance(num_threads, int)
                                        or num_threads < 1):
            raise ValueError(f"num_threads must be None or a positive integer, got {num_threads!r}.")
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        spec = MODEL_SPECS[self.NAME]
        self.model = mujoco.MjModel.from_xml_path(os.path.join(ASSETS_DIR, spec.xml_file))
        self._frame_skip = spec.frame_skip  # not `frame_skip`: EnvBase would append a FrameSkipTransform
        self.dt = self.model.opt.timestep * self._frame_skip  # same float as gymnasium's env.dt
        self.reset_noise_scale = spec.reset_noise_scale
        m = self.model
        if num_threads is None:
            num_threads = len(os.sched_getaffinity(0))
        num_threads = max(1, min(num_threads, num_envs // _MIN_COPIES_PER_THREAD))
        self.physics_threads = num_threads  # read by umrl.envs.threads.torch_threads_beside_physics
        # State rows [B, nstate] float64 of MuJoCo's batch; row i is written only by the thread stepping copy i.
        self._sim = mujoco.batch.Batch(m, num_envs, nthread=num_threads)
        self._state = self._sim.state
        qpos = _state_slice(m, mujoco.mjtState.mjSTATE_QPOS)
        self._qstate = self._state[:, qpos.start : qpos.start + m.nq + m.nv]  # view: qpos then qvel
        self._ctrl = self._sim.bind("ctrl")
        self._body_xy = np.zeros((num_envs, 2))  # gymnasium's data.body(1).xpos[:2]
        self._com_xy = np.zeros((num_envs, 2))  # torso_com_xy after each step (the reference's centre of mass)
        self._cfrc_ext = np.zeros((num_envs, m.nbody, 6))
        self._xpos = self._sim.bind("xpos")  # refreshed by every batch call on a copy (resets, set_mj_state)
        self._subtree_com = self._sim.bind("subtree_com")  # likewise
        self._workers, self._pool = [], None
        if self._reads_body_and_contacts:
            bounds = np.linspace(0, num_envs, num_threads + 1).astype(int)
            # One worker per thread: its MjData and the (state, torso x-y, contact forces, centre-of-mass x-y) rows
            # of its copies.
            rows = list(zip(self._state, self._body_xy, self._cfrc_ext, self._com_xy))
            self._workers = [(mujoco.MjData(m), rows[lo:hi]) for lo, hi in itertools.pairwise(bounds)]
            self._pool = ThreadPoolExecutor(num_threads) if num_threads > 1 else None
        data = mujoco.MjData(m)
        self._init_qpos, self._init_qvel = data.qpos.copy(), data.qvel.copy()
        self._rngs = [np.random.default_rng(seed)]  # one per group of copies (seed_copies), else one for all
        self._make_specs()

    # ----------------------------------------------------------------------------------------------------- specs
    def _make_specs(self) -> None:
        B, dev = self.batch_size[0], self.device
        obs = physics_spec(self.NAME, B, dev)
        obs["observation"] = Unbounded((B, self.obs_dim), dtype=torch.float32, device=dev)
        self.observation_spec = obs
        self.action_spec = Bounded(-1.0, 1.0, (B, self.model.nu), dtype=torch.float32, device=dev)
        self.reward_spec = Unbounded((B, 1), dtype=torch.float32, device=dev)
        self.done_spec = Composite(
            {
                k: Categorical(2, (B, 1), dtype=torch.bool, device=dev)
                for k in ("done", "terminated", "truncated")
            },
            shape=(B,),
            device=dev,
        )

    @property
    def obs_dim(self) -> int:
        return self._observe().shape[-1]

    # ----------------------------------------------------------------------------------------------- subclass API
    def _observe(self) -> np.ndarray:
        """Observation ``[B, obs_dim]`` float64 from the state buffers."""
        raise NotImplementedError

    def _step_values(
        self, action: np.ndarray, qpos_before: np.ndarray, xy_before: np.ndarray
    ) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
        """``(env_reward [B], {physics key: [B, width]}, terminated [B] bool)`` after a step, as gymnasium does."""
        raise NotImplementedError

    # --------------------------------------------------------------------------------------------------- physics
    def _advance(self) -> None:
        """Advance every copy by ``frame_skip`` ``mj_step`` calls from its state row (controls already written)."""
        if not self._reads_body_and_contacts:
            self._sim.step(nstep=self._frame_skip)
        elif self._pool is None:
            self._advance_copies(self._workers[0])
        else:
            list(self._pool.map(self._advance_copies, self._workers))

    def _advance_copies(self, worker) -> None:
        """Step each copy of ``worker``: load its state, ``mj_step`` ``frame_skip`` times, store the state back."""
        (data, rows), model, nstep = worker, self.model, self._frame_skip
        xpos, cfrc_ext = data.xpos[1, :2], data.cfrc_ext
        for state, body_xy, cfrc, com_xy in rows:
            mujoco.mj_setState(model, data, state, _STATE)
            mujoco.mj_step(model, data, nstep)
            mujoco.mj_getState(model, data, state, _STATE)
            # the mj_rnePostConstraint call is gymnasium's MujocoEnv._step_mujoco_simulation's
            mujoco.mj_rnePostConstraint(model, data)
            body_xy[:] = xpos
            cfrc[:] = cfrc_ext
            com_xy[:] = torso_com_xy(model, data)  # last: it overwrites data.xpos

    def _set_copies(self, ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray, *, reset: bool) -> None:
        """Gymnasium's ``set_state`` (after ``mj_resetData`` if ``reset``) for the sorted copies ``ids``.

        ``mj_forward`` leaves the contact forces alone: a reset zeroes them (``mj_resetData``), ``set_state``
        mid-episode keeps the copy's last ones, as gymnasium's ``MjData`` does.
        """
        if reset:
            self._sim.reset(ids, stage=mujoco.mjtStage.mjSTAGE_NONE)
            self._cfrc_ext[ids] = 0.0
        self._qstate[ids] = np.concatenate([qpos, qvel], axis=-1)
        self._sim.forward(ids)
        self._body_xy[ids] = self._xpos[ids, 1, :2]
        self._com_xy[ids] = self._subtree_com[ids, TORSO, :2]

    def set_mj_state(self, qpos: np.ndarray, qvel: np.ndarray, env_ids=None) -> None:
        """Gymnasium's ``set_state`` for copies ``env_ids`` (default all): ``qpos`` ``[n, nq]``, ``qvel`` ``[n, nv]``."""
        B = self.batch_size[0]
        ids = np.arange(B) if env_ids is None else np.asarray(env_ids, dtype=np.int64).reshape(-1)
        if ids.size and (ids.min() < 0 or ids.max() >= B or np.unique(ids).size != ids.size):
            raise ValueError(f"env_ids must be distinct copies in [0, {B}), got {ids.tolist()}.")
        qpos, qvel = np.atleast_2d(qpos), np.atleast_2d(qvel)
        if qpos.shape != (len(ids), self.model.nq) or qvel.shape != (len(ids), self.model.nv):
            raise ValueError(
                f"expected qpos [{len(ids)}, {self.model.nq}] and qvel [{len(ids)}, {self.model.nv}], "
                f"got {list(qpos.shape)} and {list(qvel.shape)}."
            )
        order = np.argsort(ids)
        self._set_copies(ids[order], qpos[order], qvel[order], reset=False)

    # ----------------------------------------------------------------------------------------------- reset noise
    def seed_copies(self, seeds: Sequence[int]) -> None:
        """Draw the reset noise of each of ``len(seeds)`` equal groups of consecutive copies from its own generator,
        seeded by ``seeds[g]``: a multi-seed run's copies of seed ``s`` see the noise of seed ``s`` alone, whatever
        the other groups do (``seeds=[s]`` is ``set_seed(s)``)."""
        B = self.batch_size[0]
        if not seeds or B % len(seeds):
            raise ValueError(f"seeds must split the {B} copies into equal groups, got {len(seeds)} seeds.")
        self._rngs = [np.random.default_rng(seed) for seed in seeds]

    @property
    def rng_state(self) -> dict | list[dict]:
        """State of the reset-noise generator (numpy ``PCG64`` ``bit_generator.state``: a new dict at each read; the
        setter copies it and refuses another generator's state); a list of them after :meth:`seed_copies` with
        several seeds."""
        states = [rng.bit_generator.state for rng in self._rngs]
        return states[0] if len(states) == 1 else states

    @rng_state.setter
    def rng_state(self, state: dict | list[dict]) -> None:
        states = state if isinstance(state, list) else [state]
        if len(states) != len(self._rngs):
            raise ValueError(f"expected {len(self._rngs)} reset-noise generator states, got {len(states)}.")
        for rng, one in zip(self._rngs, states):
            rng.bit_generator.state = one

    def get_extra_state(self) -> dict:
        """``nn.Module`` extra state, so ``state_dict()`` carries the reset-noise generator."""
        return {"reset_rng": self.rng_state}

    def set_extra_state(self, state: dict) -> None:
        if not isinstance(state, dict) or "reset_rng" not in state:
            raise ValueError(f"expected extra state {{'reset_rng': ...}}, got keys {list(state)!r:.200}.")
        self.rng_state = state["reset_rng"]

    # ------------------------------------------------------------------------------------------ episodes in progress
    def episode_state(self) -> dict[str, np.ndarray]:
        """Every copy where it stands (copies, float64): ``"state"`` ``[B, nstate]`` the integration state (time,
        qpos, qvel, act, warm start, controls, applied forces), and what the next step reads of the last one:
        ``"body_xy"`` ``[B, 2]``, ``"com_xy"`` ``[B, 2]``, ``"cfrc_ext"`` ``[B, nbody, 6]``."""
        return {"state": self._state.copy(), "body_xy": self._body_xy.copy(), "com_xy": self._com_xy.copy(),
                "cfrc_ext": self._cfrc_ext.copy()}

    def load_episode_state(self, state: dict[str, np.ndarray]) -> None:
        """Put every copy where :meth:`episode_state` took it (from an env of the same model and batch size);
        ``ValueError`` naming the entry whose shape differs, before anything is written."""
        targets = {"state": self._state, "body_xy": self._body_xy, "com_xy": self._com_xy,
                   "cfrc_ext": self._cfrc_ext}
        for key, target in targets.items():
            found = list(np.shape(state[key])) if key in state else "none"
            if found != list(target.shape):
                raise ValueError(f"episode state {key!r} of a {self.NAME} env of {self.batch_size[0]} copies must "
                                 f"have shape {list(target.shape)}, got {found}.")
        for key, target in targets.items():
            target[...] = state[key]

    # ---------------------------------------------------------------------------------------------- EnvBase API
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        B = self.batch_size[0]
        ids = np.arange(B) if mask is None else np.flatnonzero(mask.reshape(B).cpu().numpy())
        s = self.reset_noise_scale
        # gymnasium's reset_model: uniform qpos noise, then standard-normal qvel noise, from one generator per group
        groups = np.split(ids, np.searchsorted(ids, np.arange(1, len(self._rngs)) * (B // len(self._rngs))))
        qpos = np.concatenate([rng.uniform(low=-s, high=s, size=(len(g), self.model.nq))
                               for rng, g in zip(self._rngs, groups)]) + self._init_qpos
        qvel = np.concatenate([s * rng.standard_normal((len(g), self.model.nv))
                               for rng, g in zip(self._rngs, groups)]) + self._init_qvel
        self._set_copies(ids, qpos, qvel, reset=True)
        return self._output(np.zeros(B), self._physics_at_reset(), np.zeros(B, dtype=bool))

    def _physics_at_reset(self) -> dict[str, np.ndarray]:
        """Physics keys at reset: positions from the state; velocities and reward terms 0 (as in gymnasium's info)."""
        B = self.batch_size[0]
        out = {k: np.zeros((B, w)) for k, w in physics_keys(self.NAME).items()}
        position_key = "xy_position" if "xy_position" in out else "x_position"
        out[position_key] = self._qstate[:, : out[position_key].shape[1]]
        if "xy_com" in out:
            out["xy_com"] = self._com_xy.copy()
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").detach().to("cpu", torch.float32).numpy()
        qpos_before = self._qstate[:, : self.model.nq].copy()
        xy_before = self._body_xy.copy()
        self._ctrl[:] = action
        self._advance()
        env_reward, physics, terminated = self._step_values(action, qpos_before, xy_before)
        out = self._output(env_reward, physics, terminated, reward=True)
        return out

    def _output(self, env_reward, physics, terminated, *, reward: bool = False) -> TensorDictBase:
        """The step/reset TensorDict, built on CPU and put on the env's device as it is built (a device-less
        TensorDict's ``.to`` costs ~0.1 ms a step on a CPU)."""
        B = self.batch_size[0]

        def f32(x: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.asarray(x, dtype=np.float32).reshape(B, -1))

        done = torch.from_numpy(np.asarray(terminated, dtype=bool).reshape(B, 1))
        values = {
            "observation": f32(self._observe()),
            "env_reward": f32(env_reward),
            **{k: f32(v) for k, v in physics.items()},
            "done": done,
            "terminated": done.clone(),
            "truncated": torch.zeros(B, 1, dtype=torch.bool),
        }
        if reward:
            values["reward"] = torch.zeros(B, 1)
        return TensorDict(values, batch_size=self.batch_size, device=self.device)

    def _set_seed(self, seed: int | None) -> None:
        self._rngs = [np.random.default_rng(seed)]

    def close(self, *, raise_if_closed: bool = True) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        super().close(raise_if_closed=raise_if_closed)


class HalfCheetahBatchedEnv(BatchedMujocoEnv):
    """``HalfCheetah-v5`` (default kwargs): obs 17 (qpos without rootx, qvel), act 6, never terminates.

    ``env_reward = x_velocity - 0.1 * |a|^2`` with ``x_velocity = (rootx' - rootx) / dt``, ``dt = 0.05``.
    """

    NAME = "half_cheetah"
    FORWARD_REWARD_WEIGHT = 1.0
    CTRL_COST_WEIGHT = 0.1

    def _observe(self) -> np.ndarray:
        return self._qstate[:, 1:]

    def _step_values(self, action, qpos_before, xy_before):
        x_after = self._qstate[:, 0]
        x_velocity = (x_after - qpos_before[:, 0]) / self.dt
        ctrl_cost = self.CTRL_COST_WEIGHT * np.sum(np.square(action), axis=-1)
        env_reward = self.FORWARD_REWARD_WEIGHT * x_velocity - ctrl_cost
        physics = {"x_position": x_after, "x_velocity": x_velocity}
        return env_reward, physics, np.zeros(len(action), dtype=bool)


class AntBatchedEnv(BatchedMujocoEnv):
    """``Ant-v5`` (default kwargs): obs 105, act 8.

    Observation: gymnasium's default, the one the paper states (the DIAYN code's Ant: x-y position excluded, contact
    forces included): qpos without the torso's x-y (13), qvel (14), external contact forces of bodies 1..13 clipped
    to [-1, 1] (78). The paper's 111 is gym's ``Ant-v1``, which also lists the world body's 6 contact-force entries
    (always 0; v5 drops them). The x-y position is the physics key ``"xy_position"`` (coverage) and the centre of mass
    ``"xy_com"`` (:func:`torso_com_xy`, the task reward's).
    ``env_reward = x_velocity + healthy - 0.5 |a|^2 - 5e-4 |clip(cfrc_ext)|^2``, where ``x_velocity`` is the torso
    body's x displacement over ``dt = 0.05`` as gymnasium measures it (``data.body(1).xpos``), ``healthy`` is 1 when
    the state is finite and the torso height ``qpos[2]`` lies in [0.2, 1.0]; unhealthy copies terminate.
    """

    NAME = "ant"
    _reads_body_and_contacts = True
    FORWARD_REWARD_WEIGHT = 1.0
    CTRL_COST_WEIGHT = 0.5
    CONTACT_COST_WEIGHT = 5e-4
    HEALTHY_REWARD = 1.0
    HEALTHY_Z_RANGE = (0.2, 1.0)
    CONTACT_FORCE_RANGE = (-1.0, 1.0)

    def _contact_forces(self) -> np.ndarray:
        return np.clip(self._cfrc_ext, *self.CONTACT_FORCE_RANGE)

    def _observe(self) -> np.ndarray:
        contact = self._contact_forces()[:, 1:].reshape(self.batch_size[0], -1)
        return np.concatenate([self._qstate[:, 2:], contact], axis=-1)

    def _step_values(self, action, qpos_before, xy_before):
        x_velocity = (self._body_xy[:, 0] - xy_before[:, 0]) / self.dt
        z = self._qstate[:, 2]
        healthy = (
            np.isfinite(self._qstate).all(-1)
            & (self.HEALTHY_Z_RANGE[0] <= z)
            & (z <= self.HEALTHY_Z_RANGE[1])
        )
        healthy_reward = healthy * self.HEALTHY_REWARD
        ctrl_cost = self.CTRL_COST_WEIGHT * np.sum(np.square(action), axis=-1)
        contact_cost = self.CONTACT_COST_WEIGHT * np.sum(np.square(self._contact_forces()), axis=(-2, -1))
        env_reward = (x_velocity * self.FORWARD_REWARD_WEIGHT + healthy_reward) - (ctrl_cost + contact_cost)
        physics = {
            "xy_position": self._qstate[:, :2],
            "xy_com": self._com_xy.copy(),
            "x_velocity": x_velocity,
            "reward_survive": healthy_reward,
            "reward_contact": -contact_cost,
        }
        return env_reward, physics, ~healthy


BATCHED_ENVS: dict[str, type[BatchedMujocoEnv]] = {
    "half_cheetah": HalfCheetahBatchedEnv,
    "ant": AntBatchedEnv,
}
