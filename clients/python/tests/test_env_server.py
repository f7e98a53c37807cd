"""prac_client.env_server: gymnasium over dm_env_rpc, played by dm_env_rpc's own client and
trained on by `prac train --env-server`."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import time
from typing import Iterator

import grpc
import gymnasium
import numpy as np
import pytest
from dm_env import StepType
from dm_env_rpc.v1 import connection as dm_connection
from dm_env_rpc.v1 import dm_env_adaptor, error
from dm_env_rpc.v1 import dm_env_rpc_pb2 as pb
from dm_env_rpc.v1 import tensor_utils
from google.rpc import code_pb2

from conftest import prac_bin
from prac_client.env_server import check_spaces


class EnvServer:
    def __init__(self, env_id: str, *args: str) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "prac_client.env_server", "--env", env_id, "--listen", "127.0.0.1:0", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        if not line.startswith("listening on "):
            self.process.kill()
            raise RuntimeError(f"env server did not start: {line!r} {self.process.communicate()[1]}")
        self.address = line.removeprefix("listening on ").strip()

    def stop(self) -> None:
        self.process.kill()
        self.process.wait(10)


@pytest.fixture
def pendulum() -> Iterator[EnvServer]:
    server = EnvServer("Pendulum-v1", "--seed", "5")
    yield server
    server.stop()


def connect(address: str) -> dm_connection.Connection:
    return dm_connection.Connection(grpc.insecure_channel(address))


def test_dm_env_rpcs_own_client_plays_episodes_with_seeds_and_truncation(pendulum: EnvServer) -> None:
    conn = connect(pendulum.address)
    env, world = dm_env_adaptor.create_and_join_world(
        conn, create_world_settings={"seed": np.int64(11)}, join_world_settings={}
    )
    spec = env.action_spec()["action"]
    assert spec.shape == (1,) and np.all(spec.minimum == -2.0) and np.all(spec.maximum == 2.0)
    assert env.observation_spec()["observation"].shape == (3,)

    first = env.reset()
    assert first.step_type == StepType.FIRST
    steps, total = 0, 0.0
    while True:
        timestep = env.step({"action": np.array([1.0], np.float32)})
        steps += 1
        total += timestep.reward
        if timestep.last():
            break
    # Pendulum-v1 is truncated at 200 steps: LAST with discount 1 (not a terminal state).
    assert steps == 200 and timestep.discount == 1.0
    assert -2000 < total < 0
    # A step after the episode's end starts the next one without a reset.
    assert env.step({"action": np.array([0.0], np.float32)}).step_type == StepType.FIRST
    env.close()
    conn.send(pb.DestroyWorldRequest(world_name=world))

    # The same world seed gives the same first observation.
    again, world = dm_env_adaptor.create_and_join_world(conn, create_world_settings={"seed": np.int64(11)}, join_world_settings={})
    np.testing.assert_array_equal(again.reset().observation["observation"], first.observation["observation"])
    again.close()
    conn.close()


def step_request(values: list[float], dtype: type = np.float32, shape: list[int] | None = None) -> pb.StepRequest:
    tensor = tensor_utils.pack_tensor(np.asarray(values, dtype=dtype))
    if shape is not None:
        del tensor.shape[:]
        tensor.shape.extend(shape)
    return pb.StepRequest(actions={1: tensor}, requested_observations=[1, 2])


def test_bad_requests_are_refused_and_change_nothing(pendulum: EnvServer) -> None:
    conn = connect(pendulum.address)
    with pytest.raises(error.DmEnvRpcError) as e:
        conn.send(pb.StepRequest())
    assert e.value.code == code_pb2.FAILED_PRECONDITION and "join" in e.value.message
    with pytest.raises(error.DmEnvRpcError) as e:
        conn.send(pb.JoinWorldRequest(world_name="nowhere"))
    assert e.value.code == code_pb2.NOT_FOUND
    with pytest.raises(error.DmEnvRpcError) as e:
        conn.send(pb.CreateWorldRequest(settings={"speed": tensor_utils.pack_tensor(1.0)}))
    assert "unknown settings ['speed']" in e.value.message

    world = conn.send(pb.CreateWorldRequest()).world_name
    conn.send(pb.JoinWorldRequest(world_name=world))
    start = conn.send(pb.StepRequest(requested_observations=[1]))
    assert start.state == pb.EnvironmentStateType.RUNNING
    bad = {
        "shape": step_request([0.5, 0.5]),
        "dtype": step_request([0.5], np.float64),
        "nan": step_request([float("nan")]),
        "out of bounds": step_request([2.5]),
        "uid": pb.StepRequest(actions={7: tensor_utils.pack_tensor(np.zeros(1, np.float32))}),
        "observation uid": pb.StepRequest(actions=step_request([0.5]).actions, requested_observations=[99]),
    }
    for what, request in bad.items():
        with pytest.raises(error.DmEnvRpcError) as e:
            conn.send(request)
        assert e.value.code == code_pb2.INVALID_ARGUMENT, what
    # None of them stepped: a good action from the start state gives what a fresh world gives.
    after = conn.send(step_request([0.5]))
    other = conn.send(pb.CreateWorldRequest()).world_name
    conn.send(pb.LeaveWorldRequest())
    conn.send(pb.JoinWorldRequest(world_name=other))
    conn.send(pb.StepRequest())
    fresh = conn.send(step_request([0.5]))
    assert after.observations[2] == fresh.observations[2]
    np.testing.assert_array_equal(tensor_utils.unpack_tensor(after.observations[1]), tensor_utils.unpack_tensor(fresh.observations[1]))
    conn.close()


def test_discrete_and_unbounded_action_spaces_are_refused_at_start() -> None:
    class Unbounded:
        action_space = gymnasium.spaces.Box(-np.inf, np.inf, (2,))
        observation_space = gymnasium.spaces.Box(-1.0, 1.0, (3,))

    with pytest.raises(ValueError, match="unbounded"):
        check_spaces(Unbounded(), "Unbounded-v0")
    for env_id, words in [("CartPole-v1", "Discrete"), ("MountainCar-v0", "Discrete")]:
        done = subprocess.run(
            [sys.executable, "-m", "prac_client.env_server", "--env", env_id, "--listen", "127.0.0.1:0"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 2
        assert words in done.stderr and "continuous (Box) action spaces only" in done.stderr


def train(address: str, out: pathlib.Path, steps: int, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            prac_bin(), "train", "--env-server", address, "--steps", str(steps), "--learning-starts", "100",
            "--eval-every", "200", "--eval-episodes", "1", "--value-episodes", "1",
            "--out", str(out), "--quiet", *extra,
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_prac_trains_on_a_served_env_and_names_it_in_the_bundle(pendulum: EnvServer, tmp_path: pathlib.Path) -> None:
    out = tmp_path / "pendulum.safetensors"
    done = train(pendulum.address, out, 400)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["steps"] == 400 and report["episodes"] == 2
    manifest = json.loads(subprocess.run([prac_bin(), "inspect", str(out), "--json"], capture_output=True, text=True, check=True).stdout)
    assert manifest["domain"] == "Pendulum-v1" and manifest["obs_dim"] == 3 and manifest["act_dim"] == 1
    assert (tmp_path / "pendulum.train.csv").read_text().count("\n") == 3  # header and 2 episodes

    # Resuming on an environment of other sizes is refused, the checkpoint untouched.
    other = EnvServer("MountainCarContinuous-v0")
    try:
        checkpoint = sorted(p.name for p in (tmp_path / "pendulum.ckpt").iterdir())
        done = train(other.address, out, 600, "--resume")
        assert done.returncode != 0
        assert "was trained on 3 observation and 1 action values; this environment has 2 and 1" in done.stderr
        assert sorted(p.name for p in (tmp_path / "pendulum.ckpt").iterdir()) == checkpoint
    finally:
        other.stop()


def test_a_server_that_disappears_mid_run_is_named_and_the_checkpoint_resumes(tmp_path: pathlib.Path) -> None:
    server = EnvServer("Pendulum-v1")
    out = tmp_path / "p.safetensors"
    run = subprocess.Popen(
        [
            prac_bin(), "train", "--env-server", server.address, "--steps", "100000", "--learning-starts", "100",
            "--checkpoint-every", "1s", "--eval-every", "100000", "--eval-episodes", "1", "--value-episodes", "1",
            "--out", str(out), "--quiet",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    state = tmp_path / "p.ckpt" / "state.json"
    deadline = time.monotonic() + 120
    while not state.exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert state.exists(), "no checkpoint within 120 s"
    server.stop()
    _, stderr = run.communicate(timeout=120)
    assert run.returncode != 0
    assert f"the environment server at {server.address}" in stderr, stderr

    again = EnvServer("Pendulum-v1")
    try:
        step = json.loads(state.read_text())["progress"]["step"]
        done = train(again.address, out, step + 200, "--resume")
        assert done.returncode == 0, done.stderr
        assert json.loads(done.stdout)["steps"] == step + 200
    finally:
        again.stop()


@pytest.mark.skipif(
    not os.environ.get("PRAC_SLOW_TESTS"),
    reason="trains for about 6 minutes: PRAC_SLOW_TESTS=1 runs it",
)
def test_slow_pendulum_trained_over_the_protocol_reaches_minus_200(tmp_path: pathlib.Path) -> None:
    server = EnvServer("Pendulum-v1")
    try:
        out = tmp_path / "pendulum.safetensors"
        done = subprocess.run(
            [prac_bin(), "train", "--env-server", server.address, "--steps", "20000", "--eval-every", "5000",
             "--out", str(out), "--quiet"],
            capture_output=True,
            text=True,
            timeout=3600,
        )
        assert done.returncode == 0, done.stderr
        report = json.loads(done.stdout)
        # As the built-in pendulum domain's bundle: a mean deterministic return of at least -200.
        assert report["eval_return_mean"] >= -200, report
    finally:
        server.stop()
