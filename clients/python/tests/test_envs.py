"""prac_client.envs: prac's domains as gymnasium envs over `prac env-serve`."""

from __future__ import annotations

import json
import pathlib
import shutil
import subprocess
import warnings
from typing import Iterator

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import prac_client.envs
from conftest import REPO, Server, prac_bin
from prac_client import Client
from prac_client.envs import PracEnv
from prac_client.gym import run_episode


@pytest.fixture
def hopper() -> Iterator[gymnasium.Env]:  # type: ignore[type-arg]
    env = gymnasium.make("prac/Hopper-v0", prac_bin=prac_bin())
    yield env
    env.close()


@pytest.mark.parametrize("env_id", sorted(prac_client.envs.ENVS))
def test_every_domain_passes_gymnasiums_env_checker(env_id: str) -> None:
    env = gymnasium.make(env_id, prac_bin=prac_bin())
    try:
        with warnings.catch_warnings():
            # The checker's advice to use symmetric, normalised spaces does not apply to
            # the pendulum's torque in [-2, 2], which is gymnasium's own Pendulum's.
            warnings.filterwarnings("ignore", message=".*symmetric and normalized space.*")
            check_env(env.unwrapped, skip_render_check=True)
    finally:
        env.close()


def test_seeds_are_prac_episodes_and_replay_exactly(hopper: gymnasium.Env) -> None:  # type: ignore[type-arg]
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(60, 3)).astype(np.float32)

    def play(seed: int | None) -> tuple[list[np.ndarray], list[float], int]:
        obs, info = hopper.reset(seed=seed)
        observations, rewards = [obs], []
        for a in actions:
            obs, reward, terminated, truncated, _ = hopper.step(a)
            observations.append(obs)
            rewards.append(reward)
            if terminated or truncated:
                break
        return observations, rewards, info["episode_seed"]

    first, first_rewards, seed = play(7)
    assert seed == 7
    second, second_rewards, _ = play(None)
    assert play(7)[0][0].tobytes() == first[0].tobytes()
    again, again_rewards, _ = play(7)
    assert [o.tobytes() for o in again] == [o.tobytes() for o in first]
    assert again_rewards == first_rewards
    # reset() after seed 7 is episode 8.
    assert play(8)[0][0].tobytes() == second[0].tobytes()


def test_bad_actions_and_steps_out_of_an_episode_are_clear_errors(hopper: gymnasium.Env) -> None:  # type: ignore[type-arg]
    # gymnasium's wrappers refuse a step before the first reset; the env itself says so too.
    with pytest.raises(RuntimeError, match="call reset"):
        hopper.unwrapped.step(np.zeros(3, np.float32))
    hopper.reset(seed=1)
    with pytest.raises(ValueError, match="non-finite"):
        hopper.step(np.array([0.0, np.nan, 0.0], np.float32))
    with pytest.raises(ValueError):
        hopper.step(np.zeros(4, np.float32))
    # Out-of-bounds actions are clipped, as PyBullet's robots clip theirs.
    obs, *_ = hopper.step(np.full(3, 5.0, np.float32))
    hopper.reset(seed=1)
    clipped, *_ = hopper.step(np.ones(3, np.float32))
    assert obs.tobytes() == clipped.tobytes()


def test_episodes_end_by_prac_s_step_limit_and_a_step_after_asks_for_reset() -> None:
    env = gymnasium.make("prac/Pendulum-v0", prac_bin=prac_bin())
    try:
        env.reset(seed=0)
        ends = [env.step(np.zeros(1, np.float32))[2:4] for _ in range(200)]
        assert ends[-1] == (False, True) and all(end == (False, False) for end in ends[:-1])
        with pytest.raises(RuntimeError, match="episode is over"):
            env.step(np.zeros(1, np.float32))
    finally:
        env.close()


def test_a_running_server_is_shared_and_checked_for_its_domain() -> None:
    process = subprocess.Popen(
        [prac_bin(), "env-serve", "--domain", "pendulum", "--listen", "127.0.0.1:0"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        address = process.stdout.readline().removeprefix("listening on ").strip()
        a = PracEnv("pendulum", server=address)
        b = PracEnv("pendulum", server=address)
        obs_a, _ = a.reset(seed=3)
        obs_b, _ = b.reset(seed=3)
        assert obs_a.tobytes() == obs_b.tobytes()
        # Worlds are separate: a's step does not move b's pendulum.
        stepped_a = a.step(np.array([1.0], np.float32))[0]
        stepped_b = b.step(np.array([1.0], np.float32))[0]
        assert stepped_a.tobytes() == stepped_b.tobytes()
        a.close()
        b.close()
        with pytest.raises(ValueError, match="plays 'pendulum', not 'hopper'"):
            PracEnv("hopper", server=address)
        # The server goes away mid-episode: the next step says so.
        c = PracEnv("pendulum", server=address)
        c.reset(seed=0)
        process.kill()
        process.wait(10)
        with pytest.raises(ConnectionError, match="env server at .* failed"):
            for _ in range(5):
                c.step(np.zeros(1, np.float32))
        c.close()
    finally:
        process.kill()
        process.wait(10)


def test_a_missing_binary_or_domain_says_what_to_do(tmp_path: pathlib.Path) -> None:
    with pytest.raises(RuntimeError, match="unknown domain 'rocket'"):
        PracEnv("rocket", prac_bin=prac_bin())
    with pytest.raises(FileNotFoundError):
        PracEnv("hopper", prac_bin=str(tmp_path / "no-prac"))


def test_a_served_bundle_plays_the_served_domain_as_prac_evaluate_does(tmp_path: pathlib.Path) -> None:
    """The shipped Hopper, served, plays prac/Hopper-v0 through Python (two protocols) with
    the return `prac evaluate` gets in-process for the same seed: max_horizon 1 executes the
    policy's own action each step."""
    shutil.copy(REPO / "bundles" / "hopper.safetensors", tmp_path / "hopper.safetensors")
    evaluated = subprocess.run(
        [prac_bin(), "evaluate", str(tmp_path / "hopper.safetensors"), "--episodes", "1", "--seed", "777000", "--json"],
        capture_output=True,
        text=True,
        check=True,
    )
    expected = json.loads(evaluated.stdout)
    server = Server(tmp_path)
    env = gymnasium.make("prac/Hopper-v0", prac_bin=prac_bin())
    try:
        with Client(server.address, timeout=10) as client, client.session("hopper", max_horizon=1) as session:
            result = run_episode(env, session, seed=777000)
    finally:
        env.close()
        server.stop()
    assert result.steps == 1000 and result.truncated and not result.terminated
    assert result.episode_return == pytest.approx(expected["policy"]["return_mean"], rel=1e-9)


def test_sb3_sac_trains_a_few_hundred_steps_on_a_prac_env() -> None:
    pytest.importorskip("torch", reason="torch is not installed (.ci/run installs it)")
    from stable_baselines3 import SAC

    env = gymnasium.make("prac/Pendulum-v0", prac_bin=prac_bin())
    try:
        model = SAC("MlpPolicy", env, learning_starts=100, batch_size=64, seed=0, verbose=0)
        model.learn(total_timesteps=300)
        assert model.num_timesteps == 300
        obs, _ = env.reset(seed=0)
        action, _ = model.predict(obs, deterministic=True)
        assert env.action_space.contains(action)
    finally:
        env.close()


def test_a_vector_env_plays_each_env_as_its_own_episodes_with_next_step_autoreset() -> None:
    num_envs, seed, steps = 3, 40, 80
    vector = gymnasium.make_vec("prac/Hopper-v0", num_envs=num_envs, prac_bin=prac_bin())
    assert isinstance(vector.unwrapped, prac_client.envs.PracVectorEnv)
    assert vector.action_space.shape == (num_envs, 3)
    assert vector.single_observation_space.shape == (15,)
    rng = np.random.default_rng(1)
    actions = rng.uniform(-1, 1, size=(steps, num_envs, 3)).astype(np.float32)
    try:
        obs, info = vector.reset(seed=seed)
        played = [[obs[i]] for i in range(num_envs)]
        seeds = [[int(s)] for s in info["episode_seed"]]
        ended = np.zeros(num_envs, dtype=bool)
        records = []
        for a in actions:
            obs, rewards, terminated, truncated, info = vector.step(a)
            records.append((a, obs, rewards, terminated, truncated, ended.copy()))
            for i in range(num_envs):
                if ended[i]:  # the next-step autoreset: a new episode, reward 0, no end
                    assert rewards[i] == 0.0 and not terminated[i] and not truncated[i]
                    seeds[i].append(int(info["episode_seed"][i]))
            ended = terminated | truncated
        assert sum(len(s) for s in seeds) > num_envs, "no episode ended: the test needs autoresets"
        assert sorted(s for per_env in seeds for s in per_env) == sorted(
            {s for per_env in seeds for s in per_env}
        ), "every episode has a seed of its own"
        assert all(per_env[1:] == [per_env[0] + num_envs * k for k in range(1, len(per_env))] for per_env in seeds)

        # Each environment of the vector is the single env replaying its seeds with its actions.
        single = PracEnv("hopper", server=vector.unwrapped.server)
        try:
            for i in range(num_envs):
                episodes = iter(seeds[i])
                expected, _ = single.reset(seed=next(episodes))
                for a, obs, rewards, terminated, truncated, was_ended in records:
                    if was_ended[i]:
                        expected, _ = single.reset(seed=next(episodes))
                        np.testing.assert_array_equal(obs[i], expected)
                        continue
                    expected, reward, term, trunc, _ = single.step(a[i])
                    np.testing.assert_array_equal(obs[i], expected)
                    assert (rewards[i], terminated[i], truncated[i]) == (reward, term, trunc)
        finally:
            single.close()

        with pytest.raises(ValueError, match="non-finite"):
            vector.step(np.full((num_envs, 3), np.nan))
        with pytest.raises(ValueError, match="one int"):
            vector.reset(seed=[1, 2, 3])
    finally:
        vector.close()
    with pytest.raises(ValueError, match="num_envs is 0"):
        gymnasium.make_vec("prac/Hopper-v0", num_envs=0, prac_bin=prac_bin())
