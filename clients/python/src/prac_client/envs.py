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

ACTION = 1
OBSERVATION, REWARD, ENV_ID = 1, 2, 4

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


class PracEnv(gym.Env[npt.NDArray[Any], npt.NDArray[Any]]):
    """One of prac's domains in a world of `prac env-serve` (see the module's doc)."""

    metadata: dict[str, Any] = {"render_modes": []}
    observation_space: gym.spaces.Box
    action_space: gym.spaces.Box

    def __init__(self, domain: str, *, server: str | None = None, prac_bin: str | None = None) -> None:
        self.domain = domain
        self._process: subprocess.Popen[str] | None = None
        self._connection: dm_connection.Connection | None = None
        self._world: str | None = None
        if server is None:
            server = self._start(_binary(prac_bin))
        self.server = server
        try:
            self._connection = dm_connection.Connection(grpc.insecure_channel(server))
            self._world = self._send(pb.CreateWorldRequest()).world_name
            specs = self._send(pb.JoinWorldRequest(world_name=self._world)).specs
            self.observation_space = _box(specs.observations[OBSERVATION])
            self.action_space = _box(specs.actions[ACTION])
            # A first step starts an episode and names the domain the server plays.
            first = self._send(pb.StepRequest(requested_observations=[ENV_ID]))
            served = tensor_utils.unpack_tensor(first.observations[ENV_ID])
            if str(served) != domain:
                raise ValueError(f"the env server at {server} plays '{served}', not '{domain}'")
        except BaseException:
            self.close()
            raise
        self._next_episode_seed: int | None = None
        self._running = False

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
        self._send(pb.ResetRequest(settings={"seed": tensor_utils.pack_tensor(episode, dtype=np.int64)}))
        started = self._send(pb.StepRequest(requested_observations=[OBSERVATION]))
        self._running = True
        return self._observation(started), {"episode_seed": episode}

    def step(
        self, action: Any
    ) -> tuple[npt.NDArray[np.float32], float, bool, bool, dict[str, Any]]:
        if not self._running:
            raise RuntimeError("the episode is over (or never started): call reset()")
        values = np.asarray(action, dtype=np.float32).reshape(self.action_space.shape)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"the action has non-finite values: {values}")
        values = np.clip(values, self.action_space.low, self.action_space.high)
        answer = self._send(
            pb.StepRequest(
                actions={ACTION: tensor_utils.pack_tensor(values, dtype=np.float32)},
                requested_observations=[OBSERVATION, REWARD],
            )
        )
        terminated = answer.state == pb.EnvironmentStateType.TERMINATED
        truncated = answer.state == pb.EnvironmentStateType.INTERRUPTED
        self._running = not (terminated or truncated)
        reward = float(tensor_utils.unpack_tensor(answer.observations[REWARD]))
        return self._observation(answer), reward, terminated, truncated, {}

    def _observation(self, answer: Any) -> npt.NDArray[np.float32]:
        values = tensor_utils.unpack_tensor(answer.observations[OBSERVATION])
        return np.asarray(values, dtype=np.float32).reshape(self.observation_space.shape)

    def _send(self, request: Any) -> Any:
        """Sends one request; a server that is gone or failing is a ConnectionError naming it
        (a refused request raises dm_env_rpc's error with the server's message)."""
        if self._connection is None:
            raise RuntimeError("the env is closed")
        try:
            return self._connection.send(request)
        except grpc.RpcError as e:
            raise ConnectionError(f"the env server at {self.server} failed: {e.details()}") from None

    def close(self) -> None:
        if self._connection is not None:
            try:
                if self._world is not None:
                    self._connection.send(pb.LeaveWorldRequest())
                    self._connection.send(pb.DestroyWorldRequest(world_name=self._world))
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

    def __del__(self) -> None:
        self.close()


for _env_id, _domain in ENVS.items():
    if _env_id not in gym.registry:
        gym.register(id=_env_id, entry_point="prac_client.envs:PracEnv", kwargs={"domain": _domain})
