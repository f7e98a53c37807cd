"""prac's domains as gymnasium environments, played over dm_env_rpc from `prac env-serve`.

    import gymnasium as gym
    import prac_client.envs  # registers prac/Hopper-v0 and the others

    env = gym.make("prac/Hopper-v0")

Importing registers ``prac/Lander-v0``, ``prac/Hopper-v0``, ``prac/Walker-v0``,
``prac/Cheetah-v0``, ``prac/Ant-v0``, ``prac/Humanoid-v0`` and ``prac/Pendulum-v0``. Each env
starts its own ``prac env-serve --domain D`` (the binary named by ``prac_bin=`` or ``PRAC_BIN``,
else ``prac`` on PATH) and stops it on ``close()``; ``server="HOST:PORT"`` plays in a new world of
a running ``prac env-serve`` of the same domain instead.

Episodes are prac's: ``reset(seed=s)`` starts the episode ``prac evaluate --seed s``,
``prac-sim`` and ``prac train`` know as seed s, and each later ``reset()`` the next seed.
Observations are float32 within the domain's documented bounds; actions are clipped to the
action space, as the PyBullet originals clip theirs; a fall terminates, the step limit
truncates. Needs the ``envs`` extra (gymnasium, dm-env-rpc).

``gym.make_vec("prac/Hopper-v0", num_envs=N)`` makes a :class:`PracVectorEnv`: N environments in
one world of ``prac env-serve`` (its ``num_envs`` setting), stepped together in one exchange on
the server's cores, with gymnasium's next-step autoreset. It is the fast way to many steps from
Python: one exchange costs a few hundred microseconds whatever N is.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from typing import Any

import grpc
import gymnasium as gym
import numpy as np
import numpy.typing as npt
from dm_env_rpc.v1 import connection as dm_connection
from dm_env_rpc.v1 import dm_env_rpc_pb2 as pb
from dm_env_rpc.v1 import tensor_spec_utils, tensor_utils
from gymnasium.vector import AutoresetMode, VectorEnv

ACTION = 1
OBSERVATION, REWARD, ENV_ID, TERMINATED, TRUNCATED = 1, 2, 4, 6, 7
MAX_NUM_ENVS = 1024

ENVS = {
    "prac/Lander-v0": "lander",
    "prac/Hopper-v0": "hopper",
    "prac/Walker-v0": "walker",
    "prac/Cheetah-v0": "cheetah",
    "prac/Ant-v0": "ant",
    "prac/Humanoid-v0": "humanoid",
    "prac/Pendulum-v0": "pendulum",
}
START_TIMEOUT_S = 30.0


def _binary(prac_bin: str | None) -> str:
    path = prac_bin or os.environ.get("PRAC_BIN") or shutil.which("prac")
    if path is None:
        raise FileNotFoundError(
            "no prac binary: pass prac_bin=, set PRAC_BIN, or put prac on PATH "
            "(cargo build --release puts it in target/release/prac)"
        )
    return path


def _box(spec: Any) -> gym.spaces.Box:
    bounds = tensor_spec_utils.bounds(spec)
    shape = tuple(spec.shape)
    low = np.broadcast_to(np.asarray(bounds.min, dtype=np.float32), shape)
    high = np.broadcast_to(np.asarray(bounds.max, dtype=np.float32), shape)
    return gym.spaces.Box(low=low, high=high, shape=shape, dtype=np.float32)


class _World:
    """A world of ``prac env-serve --domain D``: a server started here (stopped by ``close()``)
    or a running one at ``server``."""

    def __init__(
        self, domain: str, server: str | None, prac_bin: str | None, settings: dict[str, Any]
    ) -> None:
        self.domain = domain
        self._process: subprocess.Popen[str] | None = None
        self._connection: dm_connection.Connection | None = None
        self._name: str | None = None
        if server is None:
            server = self._start(_binary(prac_bin))
        self.server = server
        try:
            self._connection = dm_connection.Connection(grpc.insecure_channel(server))
            packed = {k: tensor_utils.pack_tensor(v, dtype=np.int64) for k, v in settings.items()}
            self._name = self.send(pb.CreateWorldRequest(settings=packed)).world_name
            self.specs = self.send(pb.JoinWorldRequest(world_name=self._name)).specs
            # A first step starts the episodes and names the domain the server plays.
            first = self.send(pb.StepRequest(requested_observations=[ENV_ID]))
            served = tensor_utils.unpack_tensor(first.observations[ENV_ID])
            if str(served) != domain:
                raise ValueError(f"the env server at {server} plays '{served}', not '{domain}'")
        except BaseException:
            self.close()
            raise

    def _start(self, binary: str) -> str:
        self._process = subprocess.Popen(
            [binary, "env-serve", "--domain", self.domain, "--listen", "127.0.0.1:0"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert self._process.stdout is not None
        line = self._process.stdout.readline()
        if not line.startswith("listening on "):
            self._process.kill()
            _, stderr = self._process.communicate(timeout=START_TIMEOUT_S)
            self._process = None
            raise RuntimeError(f"prac env-serve --domain {self.domain} did not start: {stderr.strip() or line!r}")
        return line.removeprefix("listening on ").strip()

    def send(self, request: Any) -> Any:
        """Sends one request; a server that is gone or failing is a ConnectionError naming it
        (a refused request raises dm_env_rpc's error with the server's message)."""
        if self._connection is None:
            raise RuntimeError("the env is closed")
        try:
            return self._connection.send(request)
        except grpc.RpcError as e:
            raise ConnectionError(f"the env server at {self.server} failed: {e.details()}") from None

    def reset(self, seed: int, requested: list[int]) -> Any:
        """Ends the episodes and starts the next ones, the first seeded with ``seed``."""
        self.send(pb.ResetRequest(settings={"seed": tensor_utils.pack_tensor(seed, dtype=np.int64)}))
        return self.send(pb.StepRequest(requested_observations=requested))

    def step(self, actions: npt.NDArray[np.float32], requested: list[int]) -> Any:
        action = pb.Tensor(floats=pb.Tensor.FloatArray(array=actions.ravel()), shape=actions.shape)
        return self.send(pb.StepRequest(actions={ACTION: action}, requested_observations=requested))

    def close(self) -> None:
        if self._connection is not None:
            try:
                if self._name is not None:
                    self._connection.send(pb.LeaveWorldRequest())
                    self._connection.send(pb.DestroyWorldRequest(world_name=self._name))
            except Exception:  # noqa: BLE001 - a server already gone has nothing left to free
                pass
            self._connection.close()
            self._connection = None
        if self._process is not None:
            self._process.kill()
            self._process.wait(10)
            for stream in (self._process.stdout, self._process.stderr):
                if stream is not None:
                    stream.close()
            self._process = None


def _floats(answer: Any, uid: int, shape: tuple[int, ...]) -> npt.NDArray[np.float32]:
    return np.asarray(answer.observations[uid].floats.array, dtype=np.float32).reshape(shape)


def _checked(action: Any, space: gym.spaces.Box) -> npt.NDArray[np.float32]:
    """The action as float32 of the space's shape, clipped to its bounds; NaN is refused."""
    values = np.asarray(action, dtype=np.float32).reshape(space.shape)
    if not np.all(np.isfinite(values)):
        raise ValueError(f"the action has non-finite values: {values}")
    return np.clip(values, space.low, space.high)


class PracEnv(gym.Env[npt.NDArray[Any], npt.NDArray[Any]]):
    """One of prac's domains in a world of `prac env-serve` (see the module's doc)."""

    metadata: dict[str, Any] = {"render_modes": []}
    observation_space: gym.spaces.Box
    action_space: gym.spaces.Box

    def __init__(self, domain: str, *, server: str | None = None, prac_bin: str | None = None) -> None:
        self.domain = domain
        self._world = _World(domain, server, prac_bin, {})
        self.server = self._world.server
        self.observation_space = _box(self._world.specs.observations[OBSERVATION])
        self.action_space = _box(self._world.specs.actions[ACTION])
        self._next_episode_seed: int | None = None
        self._running = False

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[npt.NDArray[np.float32], dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            episode = seed
        elif self._next_episode_seed is None:
            episode = int(self.np_random.integers(0, 2**62))
        else:
            episode = self._next_episode_seed
        self._next_episode_seed = episode + 1
        started = self._world.reset(episode, [OBSERVATION])
        self._running = True
        return _floats(started, OBSERVATION, self.observation_space.shape), {"episode_seed": episode}

    def step(
        self, action: Any
    ) -> tuple[npt.NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        if not self._running:
            raise RuntimeError("the episode is over (or never started): call reset()")
        answer = self._world.step(_checked(action, self.action_space), [OBSERVATION, REWARD])
        terminated = answer.state == pb.EnvironmentStateType.TERMINATED
        truncated = answer.state == pb.EnvironmentStateType.INTERRUPTED
        self._running = not (terminated or truncated)
        reward = float(answer.observations[REWARD].doubles.array[0])
        return _floats(answer, OBSERVATION, self.observation_space.shape), reward, terminated, truncated, {}

    def close(self) -> None:
        if hasattr(self, "_world"):
            self._world.close()

    def __del__(self) -> None:
        self.close()


class PracVectorEnv(VectorEnv[npt.NDArray[Any], npt.NDArray[Any], npt.NDArray[Any]]):
    """``num_envs`` of prac's domains in one world of `prac env-serve`, stepped in one exchange.

    ``reset(seed=s)`` starts episode s + i in environment i; an environment that ends starts its
    next episode at the following step (gymnasium's next-step autoreset: that step ignores its
    action and returns the new episode's first observation with reward 0), with its seed plus
    ``num_envs``, so every episode of the vector has a seed of its own. ``info["episode_seed"]``
    holds each environment's current episode seed.
    """

    metadata: dict[str, Any] = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}
    observation_space: gym.spaces.Box
    action_space: gym.spaces.Box

    def __init__(
        self, domain: str, num_envs: int, *, server: str | None = None, prac_bin: str | None = None
    ) -> None:
        if not 1 <= num_envs <= MAX_NUM_ENVS:
            raise ValueError(f"num_envs is {num_envs}; it must be in 1..={MAX_NUM_ENVS}")
        self.domain = domain
        self.num_envs = num_envs
        self._world = _World(domain, server, prac_bin, {"num_envs": num_envs})
        self.server = self._world.server
        observation = _box(self._world.specs.observations[OBSERVATION])
        action = _box(self._world.specs.actions[ACTION])
        self.observation_space, self.action_space = observation, action
        self.single_observation_space = gym.spaces.Box(observation.low[0], observation.high[0], dtype=np.float32)
        self.single_action_space = gym.spaces.Box(action.low[0], action.high[0], dtype=np.float32)
        self._episode_seeds: npt.NDArray[np.int64] | None = None
        self._ended = np.zeros(num_envs, dtype=bool)

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[npt.NDArray[np.float32], dict[str, Any]]:
        if isinstance(seed, list):
            raise ValueError("seed is one int here: environment i plays episode seed + i")
        super().reset(seed=seed)
        if seed is None:
            seed = int(self.np_random.integers(0, 2**62))
        started = self._world.reset(seed, [OBSERVATION])
        self._episode_seeds = seed + np.arange(self.num_envs, dtype=np.int64)
        self._ended[:] = False
        return _floats(started, OBSERVATION, self.observation_space.shape), {"episode_seed": self._episode_seeds.copy()}

    def step(self, actions: Any) -> tuple[
        npt.NDArray[np.float32], npt.NDArray[np.float64], npt.NDArray[np.bool_], npt.NDArray[np.bool_], dict[str, Any]
    ]:
        if self._episode_seeds is None:
            raise RuntimeError("call reset() first")
        answer = self._world.step(_checked(actions, self.action_space), [OBSERVATION, REWARD, TERMINATED, TRUNCATED])
        self._episode_seeds[self._ended] += self.num_envs
        terminated = np.asarray(answer.observations[TERMINATED].bools.array, dtype=bool)
        truncated = np.asarray(answer.observations[TRUNCATED].bools.array, dtype=bool)
        self._ended = terminated | truncated
        rewards = np.asarray(answer.observations[REWARD].doubles.array, dtype=np.float64)
        observations = _floats(answer, OBSERVATION, self.observation_space.shape)
        return observations, rewards, terminated, truncated, {"episode_seed": self._episode_seeds.copy()}

    def close_extras(self, **kwargs: Any) -> None:
        self._world.close()


for _env_id, _domain in ENVS.items():
    if _env_id not in gym.registry:
        gym.register(
            id=_env_id,
            entry_point="prac_client.envs:PracEnv",
            vector_entry_point="prac_client.envs:PracVectorEnv",
            kwargs={"domain": _domain},
        )
