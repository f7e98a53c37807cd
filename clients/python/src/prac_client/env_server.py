"""Serve a gymnasium environment over DeepMind's dm_env_rpc protocol.

    python -m prac_client.env_server --env Pendulum-v1 [--listen 127.0.0.1:50061] [--seed S]

Prints ``listening on HOST:PORT`` once it serves. ``prac train --env-server HOST:PORT`` trains on
it; any dm_env_rpc client (e.g. ``dm_env_rpc.v1.dm_env_adaptor``) can play it.

What it offers (docs/environments.md):

- Worlds: each CreateWorld makes one environment (setting ``seed``, INT64, seeds its first
  episode; the server's ``--seed`` otherwise); one agent joins a world at a time. The worlds a
  connection created are destroyed when it ends.
- Specs: the action ``action`` (FLOAT, the Box's shape and bounds); observations ``observation``
  (FLOAT, with the Box's bounds), ``reward`` and ``discount`` (DOUBLE scalars), ``env_id``
  (STRING) and ``max_episode_steps`` (INT64, where the env has a limit).
- Episodes: the first step after joining, a reset or an episode's end ignores its actions and
  starts an episode. gymnasium's ``terminated`` answers TERMINATED (discount 0), ``truncated``
  INTERRUPTED (discount 1). ResetRequest's ``seed`` setting seeds the next episode.
- Bad requests (unknown uids or settings, a wrong dtype, shape, non-finite or out-of-bounds
  action, a step before joining) are answered with an error status and change nothing.

Only continuous (Box) action spaces with finite bounds are served; others are refused at start.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import threading
from collections.abc import Iterator
from concurrent import futures
from typing import Any

import grpc
import gymnasium as gym
import numpy as np
from dm_env_rpc.v1 import dm_env_rpc_pb2 as pb
from dm_env_rpc.v1 import dm_env_rpc_pb2_grpc as pb_grpc
from dm_env_rpc.v1 import tensor_spec_utils, tensor_utils
from google.rpc import code_pb2, status_pb2

ACTION = 1
OBSERVATION, REWARD, DISCOUNT, ENV_ID, MAX_EPISODE_STEPS = 1, 2, 3, 4, 5
SETTINGS = ("seed",)
# An action this far past a bound (relative to the bound's range) is still taken, clipped:
# float32 rounding of a rescaled tanh lands just outside.
BOUND_TOLERANCE = 1e-6


class RequestError(Exception):
    """A request the server refuses; nothing changed."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


def check_spaces(env: Any, env_id: str) -> None:
    """Raises ValueError unless the env has a Box observation and a finite Box action space."""
    action_space = env.action_space
    if not isinstance(action_space, gym.spaces.Box):
        raise ValueError(
            f"{env_id}'s actions are {type(action_space).__name__}: the server offers "
            "continuous (Box) action spaces only"
        )
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        raise ValueError(f"{env_id}'s actions are unbounded: the server offers bounded actions only")
    if not isinstance(env.observation_space, gym.spaces.Box):
        raise ValueError(
            f"{env_id}'s observations are {type(env.observation_space).__name__}: the server "
            "offers Box observations only"
        )


def _bounded_spec(name: str, space: gym.spaces.Box) -> pb.TensorSpec:
    spec = pb.TensorSpec(name=name, shape=list(space.shape), dtype=pb.DataType.FLOAT)
    tensor_spec_utils.set_bounds(
        spec, np.asarray(space.low, dtype=np.float32), np.asarray(space.high, dtype=np.float32)
    )
    return spec


def _seed(settings: Any, known: tuple[str, ...] = SETTINGS) -> int | None:
    unknown = sorted(set(settings.keys()) - set(known))
    if unknown:
        raise RequestError(
            code_pb2.INVALID_ARGUMENT,
            f"unknown settings {unknown}; known: {list(known)}",
        )
    if "seed" not in settings:
        return None
    try:
        value = tensor_utils.unpack_tensor(settings["seed"])
        seed = int(np.asarray(value).reshape(-1)[0])
    except Exception as e:  # noqa: BLE001 - any malformed tensor is the client's error
        raise RequestError(code_pb2.INVALID_ARGUMENT, f"setting 'seed' is not an integer: {e}")
    if seed < 0:
        raise RequestError(code_pb2.INVALID_ARGUMENT, f"setting 'seed' is {seed}; it must be >= 0")
    return seed


class World:
    """One environment and the state of its episode."""

    def __init__(self, env_id: str, seed: int | None) -> None:
        self.env_id = env_id
        self.env = gym.make(env_id)
        check_spaces(self.env, env_id)
        self.next_seed = seed
        self.joined = False
        self.running = False
        self.observation: np.ndarray[Any, Any] = np.zeros(self.env.observation_space.shape, np.float32)
        self.reward = 0.0
        self.discount = 1.0
        action_space = self.env.action_space
        assert isinstance(action_space, gym.spaces.Box)
        self.action_space = action_space
        self.max_episode_steps = self.env.spec.max_episode_steps if self.env.spec else None

    def restart(self, seed: int | None) -> None:
        """Ends the episode: the next step starts one (seeded with `seed` where given)."""
        if seed is not None:
            self.next_seed = seed
        self.running = False

    def specs(self) -> pb.ActionObservationSpecs:
        observation_space = self.env.observation_space
        assert isinstance(observation_space, gym.spaces.Box)
        specs = pb.ActionObservationSpecs()
        specs.actions[ACTION].CopyFrom(_bounded_spec("action", self.action_space))
        specs.observations[OBSERVATION].CopyFrom(_bounded_spec("observation", observation_space))
        specs.observations[REWARD].CopyFrom(pb.TensorSpec(name="reward", dtype=pb.DataType.DOUBLE))
        specs.observations[DISCOUNT].CopyFrom(pb.TensorSpec(name="discount", dtype=pb.DataType.DOUBLE))
        specs.observations[ENV_ID].CopyFrom(pb.TensorSpec(name="env_id", dtype=pb.DataType.STRING))
        if self.max_episode_steps is not None:
            specs.observations[MAX_EPISODE_STEPS].CopyFrom(
                pb.TensorSpec(name="max_episode_steps", dtype=pb.DataType.INT64)
            )
        return specs

    def _action(self, actions: Any) -> np.ndarray[Any, Any]:
        unknown = sorted(set(actions.keys()) - {ACTION})
        if unknown:
            raise RequestError(code_pb2.INVALID_ARGUMENT, f"unknown action uids {unknown}; the action is uid {ACTION}")
        if ACTION not in actions:
            raise RequestError(code_pb2.INVALID_ARGUMENT, f"the step has no action (uid {ACTION})")
        tensor = actions[ACTION]
        if tensor.WhichOneof("payload") != "floats":
            raise RequestError(
                code_pb2.INVALID_ARGUMENT,
                f"the action must be FLOAT (floats); got {tensor.WhichOneof('payload')}",
            )
        values = np.asarray(tensor.floats.array, dtype=np.float32)
        shape = self.action_space.shape
        if list(tensor.shape) != list(shape) or values.size != int(np.prod(shape)):
            raise RequestError(
                code_pb2.INVALID_ARGUMENT,
                f"the action has shape {list(tensor.shape)} and {values.size} values; the spec's "
                f"shape is {list(shape)}",
            )
        values = values.reshape(shape)
        if not np.all(np.isfinite(values)):
            index = int(np.flatnonzero(~np.isfinite(values))[0])
            raise RequestError(
                code_pb2.INVALID_ARGUMENT,
                f"action[{index}] is {values.reshape(-1)[index]}; every value must be finite",
            )
        low, high = self.action_space.low, self.action_space.high
        slack = BOUND_TOLERANCE * (high - low)
        outside = (values < low - slack) | (values > high + slack)
        if np.any(outside):
            index = int(np.flatnonzero(outside)[0])
            raise RequestError(
                code_pb2.INVALID_ARGUMENT,
                f"action[{index}] is {values.reshape(-1)[index]}, outside "
                f"[{low.reshape(-1)[index]}, {high.reshape(-1)[index]}]",
            )
        return np.clip(values, low, high).astype(self.action_space.dtype)

    def step(self, request: pb.StepRequest) -> pb.StepResponse:
        known = {OBSERVATION, REWARD, DISCOUNT, ENV_ID} | (
            {MAX_EPISODE_STEPS} if self.max_episode_steps is not None else set()
        )
        unknown = sorted(set(request.requested_observations) - known)
        if unknown:
            raise RequestError(
                code_pb2.INVALID_ARGUMENT,
                f"unknown observation uids {unknown}; known: {sorted(known)}",
            )
        if not self.running:
            # Actions are ignored: the step starts an episode.
            observation, _ = self.env.reset(seed=self.next_seed)
            self.next_seed = None
            self.running, self.reward, self.discount = True, 0.0, 1.0
            state = pb.EnvironmentStateType.RUNNING
        else:
            action = self._action(request.actions)
            observation, reward, terminated, truncated, _ = self.env.step(action)
            self.reward = float(reward)
            self.discount = 0.0 if terminated else 1.0
            if terminated:
                state = pb.EnvironmentStateType.TERMINATED
            elif truncated:
                state = pb.EnvironmentStateType.INTERRUPTED
            else:
                state = pb.EnvironmentStateType.RUNNING
            self.running = state == pb.EnvironmentStateType.RUNNING
        self.observation = np.asarray(observation, dtype=np.float32)
        response = pb.StepResponse(state=state)
        for uid in dict.fromkeys(request.requested_observations):
            response.observations[uid].CopyFrom(self._observe(uid))
        return response

    def _observe(self, uid: int) -> pb.Tensor:
        if uid == OBSERVATION:
            return tensor_utils.pack_tensor(self.observation, dtype=np.float32)
        if uid == REWARD:
            return tensor_utils.pack_tensor(self.reward, dtype=np.float64)
        if uid == DISCOUNT:
            return tensor_utils.pack_tensor(self.discount, dtype=np.float64)
        if uid == ENV_ID:
            return tensor_utils.pack_tensor(self.env_id, dtype=np.str_)
        return tensor_utils.pack_tensor(int(self.max_episode_steps or 0), dtype=np.int64)


class EnvironmentServicer(pb_grpc.EnvironmentServicer):  # type: ignore[misc]
    """dm_env_rpc's Environment service over gymnasium environments of one id."""

    def __init__(self, env_id: str, seed: int | None) -> None:
        self.env_id = env_id
        self.seed = seed
        self.worlds: dict[str, World] = {}
        self.lock = threading.Lock()
        self.counter = itertools.count()

    def Process(self, requests: Iterator[pb.EnvironmentRequest], context: Any) -> Iterator[pb.EnvironmentResponse]:  # noqa: N802
        joined: World | None = None
        created: list[str] = []
        try:
            for request in requests:
                response = pb.EnvironmentResponse()
                try:
                    joined = self._handle(request, response, joined, created)
                except RequestError as e:
                    response.Clear()
                    response.error.CopyFrom(status_pb2.Status(code=e.code, message=e.message))
                except Exception as e:  # noqa: BLE001 - the env's own failure, reported to the client
                    response.Clear()
                    response.error.CopyFrom(
                        status_pb2.Status(code=code_pb2.INTERNAL, message=f"{type(e).__name__}: {e}")
                    )
                yield response
        finally:
            with self.lock:
                if joined is not None:
                    joined.joined = False
                for name in created:
                    world = self.worlds.pop(name, None)
                    if world is not None:
                        world.env.close()

    def _world(self, name: str) -> World:
        world = self.worlds.get(name)
        if world is None:
            raise RequestError(code_pb2.NOT_FOUND, f"no world '{name}'; known: {sorted(self.worlds)}")
        return world

    def _handle(
        self,
        request: pb.EnvironmentRequest,
        response: pb.EnvironmentResponse,
        joined: World | None,
        created: list[str],
    ) -> World | None:
        kind = request.WhichOneof("payload")
        if kind == "create_world":
            seed = _seed(request.create_world.settings)
            world = World(self.env_id, self.seed if seed is None else seed)
            with self.lock:
                name = f"{self.env_id}-{next(self.counter)}"
                self.worlds[name] = world
            created.append(name)
            response.create_world.world_name = name
            return joined
        if kind == "join_world":
            if joined is not None:
                raise RequestError(code_pb2.FAILED_PRECONDITION, "this connection has joined a world already; leave it first")
            seed = _seed(request.join_world.settings)
            with self.lock:
                world = self._world(request.join_world.world_name)
                if world.joined:
                    raise RequestError(
                        code_pb2.FAILED_PRECONDITION,
                        f"world '{request.join_world.world_name}' has an agent already (one per world)",
                    )
                world.joined = True
            world.restart(seed)
            response.join_world.specs.CopyFrom(world.specs())
            return world
        if kind == "destroy_world":
            with self.lock:
                world = self._world(request.destroy_world.world_name)
                if world.joined:
                    raise RequestError(code_pb2.FAILED_PRECONDITION, "an agent is in the world; it must leave first")
                del self.worlds[request.destroy_world.world_name]
            world.env.close()
            response.destroy_world.SetInParent()
            return joined
        if kind == "reset_world":
            with self.lock:
                world = self._world(request.reset_world.world_name)
            world.restart(_seed(request.reset_world.settings))
            response.reset_world.SetInParent()
            return joined
        if kind == "extension":
            raise RequestError(code_pb2.UNIMPLEMENTED, "this server has no extensions")
        if joined is None:
            raise RequestError(code_pb2.FAILED_PRECONDITION, f"{kind} needs a joined world: create and join one first")
        if kind == "step":
            response.step.CopyFrom(joined.step(request.step))
            return joined
        if kind == "reset":
            joined.restart(_seed(request.reset.settings))
            response.reset.specs.CopyFrom(joined.specs())
            return joined
        if kind == "leave_world":
            with self.lock:
                joined.joined = False
            response.leave_world.SetInParent()
            return None
        raise RequestError(code_pb2.INVALID_ARGUMENT, f"unknown request '{kind}'")


def serve(env_id: str, listen: str, seed: int | None, max_workers: int) -> tuple[grpc.Server, int]:
    """Starts the server; returns it and the bound port."""
    probe = gym.make(env_id)
    try:
        check_spaces(probe, env_id)
    finally:
        probe.close()
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=max_workers))
    pb_grpc.add_EnvironmentServicer_to_server(EnvironmentServicer(env_id, seed), server)
    port = server.add_insecure_port(listen)
    if port == 0:
        raise ValueError(f"cannot listen on {listen}")
    server.start()
    return server, port


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m prac_client.env_server", description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", required=True, help="gymnasium environment id, e.g. Pendulum-v1")
    parser.add_argument("--listen", default="127.0.0.1:50061", help="HOST:PORT (port 0 picks a free one)")
    parser.add_argument("--seed", type=int, default=None, help="seed of each world's first episode unless it sets one")
    parser.add_argument(
        "--max-workers",
        type=int,
        default=16,
        help="threads, hence connections served at once (each open connection holds one)",
    )
    args = parser.parse_args(argv)
    try:
        server, port = serve(args.env, args.listen, args.seed, args.max_workers)
    except (ValueError, gym.error.Error) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    host = args.listen.rsplit(":", 1)[0]
    print(f"listening on {host}:{port}", flush=True)
    try:
        server.wait_for_termination()
    except KeyboardInterrupt:
        server.stop(grace=1.0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
