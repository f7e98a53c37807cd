"""Real SB3 agents (SAC with gSDE, TD3, DDPG), trained for a few hundred steps here, exported and
served: on fresh plans the served action is SB3's deterministic `predict`. Skipped without
stable-baselines3 (pip install 'prac-client[sb3]'). With PRAC_ZOO_AGENTS set to a checkout of
DLR-RM/rl-trained-agents, the zoo's own gSDE agents are checked over an episode too."""

from __future__ import annotations

import json
import os
import pathlib
from typing import Any

import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason="stable-baselines3 and torch are not installed (prac-client[sb3])")

import gymnasium  # noqa: E402
import torch  # noqa: E402
from stable_baselines3 import DDPG, SAC, TD3  # noqa: E402

from conftest import Server  # noqa: E402
from prac_client import Client, InvalidOptions  # noqa: E402
from prac_client.bundle import from_sb3_state_dict, random_model, write_bundle  # noqa: E402
from prac_client.export_sb3 import load_sb3_zip  # noqa: E402
from prac_client.export_sb3 import main as export_main  # noqa: E402
from prac_client.record import load_sb3  # noqa: E402
from prac_client.value_scale import measure, read_bundle  # noqa: E402
from prac_client.record import main as record_main  # noqa: E402

AGENTS: dict[str, tuple[Any, dict[str, Any], str]] = {
    "sde": (SAC, {"use_sde": True}, "gaussian_sde"),
    "td3": (TD3, {}, "deterministic"),
    "ddpg": (DDPG, {}, "deterministic"),
}


@pytest.fixture(scope="module")
def agents(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Any, pathlib.Path]]:
    directory = tmp_path_factory.mktemp("sb3")
    # One thread: tiny networks, and torch's threads spin against anything else on two cores.
    torch.set_num_threads(1)
    trained = {}
    for name, (algorithm, kwargs, _) in AGENTS.items():
        env = gymnasium.make("Pendulum-v1")
        model = algorithm("MlpPolicy", env, seed=0, learning_starts=100, policy_kwargs={"net_arch": [32, 32]}, **kwargs)
        model.learn(300)
        model.save(directory / name)
        trained[name] = (model, directory / f"{name}.zip")
    return trained


def test_each_kind_exports_and_serves_sb3s_deterministic_action(
    agents: dict[str, tuple[Any, pathlib.Path]], tmp_path: pathlib.Path
) -> None:
    for name, (model, zip_file) in agents.items():
        # The export command itself, from the path without .zip as SB3 takes it.
        assert export_main([str(zip_file.with_suffix("")), "--out", str(tmp_path / f"plain-{name}.safetensors")]) == 0
        state, facts = load_sb3_zip(zip_file)
        assert facts["actor_kind"] == AGENTS[name][2], facts
        assert facts["algorithm"] == {"sde": "SAC (gSDE)", "td3": "TD3", "ddpg": "DDPG"}[name]
        tensors, manifest = from_sb3_state_dict(
            state,
            name=name,
            domain="pendulum",
            action_low=facts["action_low"],
            action_high=facts["action_high"],
            gamma=facts["gamma"],
            model=random_model(3, 1, [16], seed=1),
            actor_kind=facts["actor_kind"],
            mean_clip=facts["mean_clip"],
        )
        if name == "sde":
            assert manifest["actor"]["mean_clip"] == 2.0
        write_bundle(tmp_path / f"{name}.safetensors", tensors, manifest)
    server = Server(tmp_path)
    try:
        with Client(server.address, timeout=10) as client:
            env = gymnasium.make("Pendulum-v1")
            for name, (model, _) in agents.items():
                observations = [env.reset(seed=k)[0] for k in range(10)]
                observations += [env.observation_space.sample() for _ in range(10)]
                # Max horizon 1: every step is a fresh plan, so exactly the policy.
                with client.session(name, max_horizon=1) as session:
                    for obs in observations:
                        served = session.reset(np.asarray(obs, dtype=np.float32))
                        assert served is not None
                        expected, _ = model.predict(obs, deterministic=True)
                        np.testing.assert_allclose(served.action, expected, rtol=1e-4, atol=1e-4, err_msg=name)
                with pytest.raises(InvalidOptions, match="acts deterministically"):
                    client.session(name, sampled=True)
    finally:
        server.stop()


def test_record_plays_each_algorithm_from_its_zip(agents: dict[str, tuple[Any, pathlib.Path]], tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    for name, (_, zip_file) in agents.items():
        out = tmp_path / f"{name}.safetensors"
        assert record_main(["--env", "Pendulum-v1", "--episodes", "1", "--out", str(out), "--sb3", str(zip_file.with_suffix(""))]) == 0
        summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert summary["transitions"] == 200, (name, summary)


def test_what_is_not_a_checkpoint_is_one_line(tmp_path: pathlib.Path) -> None:
    (tmp_path / "notes.zip").write_text("not a zip")
    with pytest.raises(SystemExit, match=r"notes.zip: not a readable SB3 checkpoint \(File is not a zip file\)"):
        load_sb3_zip(tmp_path / "notes.zip")
    with pytest.raises(SystemExit, match="absent: not a readable SB3 checkpoint"):
        load_sb3_zip(tmp_path / "absent")


ZOO = os.environ.get("PRAC_ZOO_AGENTS")


@pytest.mark.skipif(ZOO is None, reason="PRAC_ZOO_AGENTS (a checkout of DLR-RM/rl-trained-agents) is not set")
@pytest.mark.parametrize("env_id", ["Pendulum-v1", "MountainCarContinuous-v0"])
def test_the_zoos_gsde_agents_serve_their_own_actions_over_an_episode(env_id: str, tmp_path: pathlib.Path) -> None:
    stem = pathlib.Path(str(ZOO)) / "sac" / f"{env_id}_1" / env_id
    state, facts = load_sb3_zip(stem)
    assert (facts["algorithm"], facts["mean_clip"]) == ("SAC (gSDE)", 2.0)
    obs_dim, act_dim = facts["obs_dim"], len(facts["action_low"])
    tensors, manifest = from_sb3_state_dict(
        state,
        name="zoo",
        domain=env_id,
        action_low=facts["action_low"],
        action_high=facts["action_high"],
        gamma=facts["gamma"],
        model=random_model(obs_dim, act_dim, [16], seed=1),
        actor_kind=facts["actor_kind"],
        mean_clip=facts["mean_clip"],
    )
    write_bundle(tmp_path / "zoo.safetensors", tensors, manifest)
    env = gymnasium.make(env_id)
    model = load_sb3(str(stem), env)
    server = Server(tmp_path)
    try:
        with Client(server.address, timeout=10) as client, client.session("zoo", max_horizon=1) as session:
            obs, _ = env.reset(seed=0)
            for step in range(200):
                served = session.step(np.asarray(obs, dtype=np.float32), new_episode=step == 0)
                expected, _ = model.predict(obs, deterministic=True)
                np.testing.assert_allclose(served.action, expected, rtol=1e-4, atol=1e-4)
                obs, _, terminated, truncated, _ = env.step(expected)
                if terminated or truncated:
                    break
    finally:
        server.stop()


def test_export_measures_the_value_scale_on_the_env(
    agents: dict[str, tuple[Any, pathlib.Path]], tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model, zip_file = agents["td3"]
    out = tmp_path / "measured.safetensors"
    assert export_main([str(zip_file), "--out", str(out), "--env", "Pendulum-v1", "--episodes", "3"]) == 0
    env = gymnasium.make("Pendulum-v1")
    v_pi, v_rand = measure(env, lambda obs: model.predict(obs, deterministic=True)[0], model.gamma, 3, 0)
    assert f"V_pi = {v_pi:.4f}, V_rand = {v_rand:.4f}" in capsys.readouterr().out
    _, manifest = read_bundle(out)
    if v_pi > v_rand:
        assert manifest["value_scale"] == {"v_pi": pytest.approx(v_pi), "v_rand": pytest.approx(v_rand)}
    else:
        assert manifest["value_scale"] is None


def _train_behind_vecnormalize(directory: pathlib.Path, norm_reward: bool) -> tuple[Any, Any, pathlib.Path]:
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    torch.set_num_threads(1)
    venv = VecNormalize(make_vec_env("Pendulum-v1", n_envs=1, seed=0), norm_obs=True, norm_reward=norm_reward, clip_obs=5.0)
    model = SAC("MlpPolicy", venv, seed=0, learning_starts=100, policy_kwargs={"net_arch": [32, 32]})
    model.learn(300)
    # The rl-zoo's layout: ENV_ID.zip beside ENV_ID/vecnormalize.pkl.
    model.save(directory / "Pendulum-v1")
    (directory / "Pendulum-v1").mkdir()
    venv.save(str(directory / "Pendulum-v1" / "vecnormalize.pkl"))
    return model, venv, directory / "Pendulum-v1.zip"


def test_an_agent_trained_behind_vecnormalize_serves_on_raw_observations(
    tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from prac_client import vecnormalize

    model, venv, zip_file = _train_behind_vecnormalize(tmp_path / "agent", norm_reward=False)
    bundles = tmp_path / "bundles"
    bundles.mkdir()
    out = bundles / "normed.safetensors"
    assert export_main([str(zip_file), "--out", str(out), "--env", "Pendulum-v1", "--episodes", "2"]) == 0
    printed = capsys.readouterr().out
    assert "observations normalised, rewards raw" in printed
    # The value scale is measured with the agent behind its statistics.
    env = gymnasium.make("Pendulum-v1")
    v_pi, v_rand = measure(env, lambda o: model.predict(venv.normalize_obs(o), deterministic=True)[0], model.gamma, 2, 0)
    assert f"V_pi = {v_pi:.4f}, V_rand = {v_rand:.4f}" in printed
    tensors, manifest = read_bundle(out)
    # Pendulum-v1's Box, recorded in the checkpoint, bounds the forecasts (format 4); the
    # normalisation is raw-observation statistics beside it.
    assert manifest["format_version"] == 4
    assert manifest["obs_bounds"] == {"low": [-1.0, -1.0, -8.0], "high": [1.0, 1.0, 8.0]}
    stats = manifest["obs_normalization"]
    np.testing.assert_allclose(stats["mean"], venv.obs_rms.mean, rtol=1e-6)
    np.testing.assert_allclose(stats["var"], venv.obs_rms.var, rtol=1e-6)
    assert (stats["clip_obs"], stats["epsilon"]) == (5.0, pytest.approx(venv.epsilon))
    # The server needs a dynamics model; it speaks raw observations.
    full_tensors, full_manifest = from_sb3_state_dict(
        load_sb3_zip(zip_file)[0],
        name="normed",
        domain="pendulum",
        action_low=manifest["action_low"],
        action_high=manifest["action_high"],
        gamma=manifest["gamma"],
        model=random_model(3, 1, [16], seed=1),
        obs_normalization=stats,
    )
    write_bundle(out, full_tensors, full_manifest)
    assert vecnormalize.read(zip_file.with_suffix("") / "vecnormalize.pkl").norm_obs
    server = Server(bundles)
    try:
        with Client(server.address, timeout=10) as client, client.session("normed", max_horizon=1) as session:
            for k in range(20):
                obs = env.reset(seed=k)[0] if k < 10 else env.observation_space.sample()
                served = session.reset(np.asarray(obs, dtype=np.float32))
                assert served is not None
                expected, _ = model.predict(venv.normalize_obs(obs), deterministic=True)
                np.testing.assert_allclose(served.action, expected, rtol=1e-4, atol=1e-4)
                # Raw observations would act otherwise: the normalisation is not a no-op.
                unnormalised, _ = model.predict(obs, deterministic=True)
                assert k >= 10 or not np.allclose(unnormalised, expected, atol=1e-3)
    finally:
        server.stop()
    # record --sb3 plays the agent behind its statistics and keeps raw observations; the path
    # without .zip names the zip even where the zoo's folder of that name sits beside it.
    recorded = tmp_path / "t.safetensors"
    stem = str(zip_file.with_suffix(""))
    assert record_main(["--env", "Pendulum-v1", "--episodes", "1", "--out", str(recorded), "--sb3", stem]) == 0
    from safetensors.numpy import load_file

    data = load_file(str(recorded))
    np.testing.assert_allclose(data["obs"][0], env.reset(seed=0)[0], rtol=1e-6)
    expected, _ = model.predict(venv.normalize_obs(data["obs"][0]), deterministic=True)
    np.testing.assert_allclose(data["action"][0], expected, rtol=1e-5, atol=1e-5)


def test_normalised_rewards_give_no_value_scale(tmp_path: pathlib.Path, capsys: pytest.CaptureFixture[str]) -> None:
    _, _, zip_file = _train_behind_vecnormalize(tmp_path, norm_reward=True)
    with pytest.raises(SystemExit, match="trained on normalised rewards"):
        export_main([str(zip_file), "--out", str(tmp_path / "x.safetensors"), "--env", "Pendulum-v1"])
    assert export_main([str(zip_file), "--out", str(tmp_path / "x.safetensors")]) == 0
    assert "the bundle has no value scale" in capsys.readouterr().out
    _, manifest = read_bundle(tmp_path / "x.safetensors")
    assert manifest["value_scale"] is None and "obs_normalization" in manifest
