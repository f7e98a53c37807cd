"""SB3 -> bundle mapping, checked without torch on a state dict with SB3's exact names."""

from __future__ import annotations

import importlib.util
import json
import pathlib
import re
import subprocess

import numpy as np
import pytest

from conftest import Server, prac_bin
import prac_client
from prac_client import Client
from prac_client.bundle import from_sb3_state_dict, random_model, random_sb3_state_dict, write_bundle
from prac_client.export_sb3 import algorithm_of
from prac_client.export_sb3 import main as export_main
from prac_client.record import gymnasium_id
from prac_client.value_scale import discounted_return, measure, read_bundle
from prac_client.value_scale import main as value_scale_main
from prac_client.export_sb3 import spaces_from_sb3_data


def numpy_actor(state: dict[str, np.ndarray], obs: np.ndarray) -> np.ndarray:
    """SB3's deterministic SAC action: tanh(mu(ReLU MLP(obs))), in [-1, 1]."""
    x = obs.astype(np.float64)
    i = 0
    while f"actor.latent_pi.{i}.weight" in state:
        x = np.maximum(state[f"actor.latent_pi.{i}.weight"] @ x + state[f"actor.latent_pi.{i}.bias"], 0.0)
        i += 2
    return np.tanh(state["actor.mu.weight"] @ x + state["actor.mu.bias"])


# What SB3 2.x writes in a SAC checkpoint's `data` for a Box(-2, 2, (1,)) action space and a
# 3-dimensional observation (trimmed to the fields read; the pickles are not touched).
SB3_DATA = {
    "policy_kwargs": {":type:": "<class 'dict'>", ":serialized:": "gAWV...", "activation_fn": "<class 'torch.nn.modules.activation.ReLU'>", "net_arch": [64, 64]},
    "observation_space": {":type:": "<class 'gymnasium.spaces.box.Box'>", ":serialized:": "gAWV...", "dtype": "float32", "_shape": [3], "low": "[-1. -1. -8.]", "high": "[1. 1. 8.]"},
    "action_space": {":type:": "<class 'gymnasium.spaces.box.Box'>", ":serialized:": "gAWV...", "dtype": "float32", "_shape": [1], "low": "[-2.]", "high": "[2.]", "low_repr": "-2.0", "high_repr": "2.0"},
    "gamma": 0.98,
    "num_timesteps": 20000,
    "seed": 7,
}


def test_sb3_data_fields_are_read_without_unpickling() -> None:
    facts = spaces_from_sb3_data(SB3_DATA)
    assert facts["obs_dim"] == 3
    np.testing.assert_array_equal(facts["action_low"], [-2.0])
    np.testing.assert_array_equal(facts["action_high"], [2.0])
    assert (facts["gamma"], facts["activation"], facts["steps"], facts["seed"]) == (0.98, "relu", 20000, 7)
    tanh = json.loads(json.dumps(SB3_DATA))
    tanh["policy_kwargs"]["activation_fn"] = "<class 'torch.nn.modules.activation.Tanh'>"
    assert spaces_from_sb3_data(tanh)["activation"] == "tanh"
    bad = json.loads(json.dumps(SB3_DATA))
    bad["policy_kwargs"]["activation_fn"] = "<class 'torch.nn.modules.activation.ELU'>"
    with pytest.raises(ValueError, match="ELU"):
        spaces_from_sb3_data(bad)


def test_export_maps_names_and_layout(tmp_path: pathlib.Path) -> None:
    state = random_sb3_state_dict(5, 2, [64, 48], seed=11)
    assert "critic_target.qf1.4.weight" in state
    tensors, manifest = from_sb3_state_dict(
        state, name="sb3", domain="toy", action_low=[-1.0, 0.0], action_high=[1.0, 4.0], gamma=0.99
    )
    assert not any(k.startswith("critic_target") for k in tensors)
    assert manifest["actor"]["hidden"] == [64, 48]
    assert manifest["critic"] == {"n_critics": 2, "hidden": [64, 48], "activation": "relu"}
    assert manifest["model"] is None
    path = tmp_path / "sb3.safetensors"
    write_bundle(path, tensors, manifest)

    # The Rust loader accepts it and reads back the same manifest.
    out = subprocess.run([prac_bin(), "inspect", str(path), "--json"], capture_output=True, text=True, check=True)
    loaded = json.loads(out.stdout)
    assert loaded["obs_dim"] == 5 and loaded["act_dim"] == 2
    assert loaded["critic"]["n_critics"] == 2 and loaded["model"] is None

    # Its forward pass at s = 0 equals SB3's deterministic action, mapped to the bounds.
    text = subprocess.run([prac_bin(), "inspect", str(path)], capture_output=True, text=True, check=True).stdout
    printed = re.search(r"pi\(s\)\s+\[([^\]]*)\]", text)
    assert printed, text
    served = np.array([float(v) for v in printed.group(1).split(",")])
    squashed = numpy_actor(state, np.zeros(5))
    expected = np.array([-1.0, 0.0]) + (squashed + 1.0) / 2.0 * np.array([2.0, 4.0])
    np.testing.assert_allclose(served, expected, rtol=1e-5, atol=1e-5)


def test_an_exported_bundle_with_a_model_serves_sb3s_actions(tmp_path: pathlib.Path) -> None:
    state = random_sb3_state_dict(3, 1, [32, 32], seed=5)
    tensors, manifest = from_sb3_state_dict(
        state,
        name="exported",
        domain="pendulum",
        action_low=[-2.0],
        action_high=[2.0],
        gamma=0.98,
        model=random_model(3, 1, [16], seed=5),
    )
    write_bundle(tmp_path / "exported.safetensors", tensors, manifest)
    server = Server(tmp_path)
    try:
        with Client(server.address, timeout=10) as client, client.session("exported") as session:
            rng = np.random.default_rng(1)
            for _ in range(5):
                obs = rng.uniform(-1, 1, 3).astype(np.float32)
                # A fresh episode: the action is pi(obs), decided now.
                result = session.reset(obs)
                assert result is not None
                expected = 2.0 * numpy_actor(state, obs)
                np.testing.assert_allclose(result.action, expected, rtol=1e-4, atol=1e-5)
    finally:
        server.stop()


@pytest.mark.skipif(importlib.util.find_spec("torch") is not None, reason="torch is installed")
def test_export_without_torch_says_what_to_install(tmp_path: pathlib.Path) -> None:
    with pytest.raises(SystemExit, match="needs torch"):
        export_main([str(tmp_path / "model.zip"), "--out", str(tmp_path / "p.safetensors")])


def sde_and_td3_state_dicts(seed: int) -> dict[str, dict[str, np.ndarray]]:
    """A SAC state dict renamed as SB3 names a clipped gSDE actor, and one as its TD3 actor."""
    sac = random_sb3_state_dict(3, 1, [32, 32], seed=seed)
    sde = {k: v for k, v in sac.items() if not k.startswith("actor.mu.") and not k.startswith("actor.log_std.")}
    sde["actor.mu.0.weight"], sde["actor.mu.0.bias"] = 4.0 * sac["actor.mu.weight"], sac["actor.mu.bias"]
    sde["actor.log_std"] = np.full((32, 1), -1.0, dtype=np.float32)
    td3 = {k: v for k, v in sac.items() if k.startswith("critic")}
    for i, prefix in enumerate(["actor.latent_pi.0", "actor.latent_pi.2", "actor.mu"]):
        td3[f"actor.mu.{2 * i}.weight"], td3[f"actor.mu.{2 * i}.bias"] = sac[f"{prefix}.weight"], sac[f"{prefix}.bias"]
    return {"sde": sde, "td3": td3, "sac": sac}


def test_gsde_and_td3_actors_export_and_serve_tanh_of_the_clipped_mean(tmp_path: pathlib.Path) -> None:
    states = sde_and_td3_state_dicts(seed=9)
    sac = states["sac"]
    for name, kind, clip in [("sde", "gaussian_sde", 2.0), ("td3", "deterministic", None)]:
        tensors, manifest = from_sb3_state_dict(
            states[name],
            name=name,
            domain="pendulum",
            action_low=[-2.0],
            action_high=[2.0],
            gamma=0.98,
            model=random_model(3, 1, [16], seed=2),
            actor_kind=kind,
            mean_clip=clip,
        )
        assert "actor.log_std.weight" not in tensors and not any(k.startswith("critic_target") for k in tensors)
        assert manifest["format_version"] == 2
        assert manifest["actor"]["kind"] == kind and manifest["actor"].get("mean_clip") == clip
        write_bundle(tmp_path / f"{name}.safetensors", tensors, manifest)
    server = Server(tmp_path)
    try:
        with Client(server.address, timeout=10) as client:
            rng = np.random.default_rng(3)
            observations = rng.uniform(-1, 1, (8, 3)).astype(np.float32)
            for name, scale, clip in [("sde", 4.0, 2.0), ("td3", 1.0, np.inf)]:
                with client.session(name, max_horizon=1) as session:
                    for obs in observations:
                        x = obs.astype(np.float64)
                        for layer in ("actor.latent_pi.0", "actor.latent_pi.2"):
                            x = np.maximum(sac[f"{layer}.weight"] @ x + sac[f"{layer}.bias"], 0.0)
                        mu = scale * sac["actor.mu.weight"] @ x + sac["actor.mu.bias"]
                        expected = 2.0 * np.tanh(np.clip(mu, -clip, clip))
                        result = session.reset(obs)
                        assert result is not None
                        np.testing.assert_allclose(result.action, expected, rtol=1e-4, atol=1e-5)
                # No distribution to sample from: a sampled session is refused with the reason.
                with pytest.raises(prac_client.InvalidOptions, match="acts deterministically"):
                    client.session(name, sampled=True)
    finally:
        server.stop()


def test_the_algorithm_comes_from_the_policy_class_and_others_are_refused() -> None:
    states = sde_and_td3_state_dicts(seed=1)
    module = lambda m: {"policy_class": {":type:": "<class 'abc.ABCMeta'>", "__module__": m}}  # noqa: E731
    assert algorithm_of(module("stable_baselines3.sac.policies"), states["sac"]) == ("SAC", "gaussian", None)
    sde_data = {**module("stable_baselines3.sac.policies"), "policy_kwargs": {"use_sde": True, "clip_mean": 1.5}}
    assert algorithm_of(sde_data, states["sde"]) == ("SAC (gSDE)", "gaussian_sde", 1.5)
    td3 = module("stable_baselines3.td3.policies")
    assert algorithm_of(td3, states["td3"]) == ("TD3", "deterministic", None)
    ddpg = {**td3, "policy_delay": 1, "target_noise_clip": 0.0}
    assert algorithm_of(ddpg, states["td3"]) == ("DDPG", "deterministic", None)
    # Old zips without the module: the weights' names tell SAC from TD3.
    assert algorithm_of({}, states["td3"])[1] == "deterministic"
    with pytest.raises(ValueError, match=r"stable_baselines3.ppo.policies: prac serves off-policy actor-critics"):
        algorithm_of(module("stable_baselines3.ppo.policies"), {"action_net.weight": np.zeros(1)})


def test_gym_mujoco_ids_play_as_gymnasium_v4(capsys: pytest.CaptureFixture[str]) -> None:
    assert gymnasium_id("Hopper-v3") == "Hopper-v4"
    assert "gymnasium's port" in capsys.readouterr().err
    assert gymnasium_id("Pendulum-v1") == "Pendulum-v1"
    assert gymnasium_id("Walker2d-v5") == "Walker2d-v5"


def test_a_value_scale_is_added_or_replaced_and_nonsense_refused(tmp_path: pathlib.Path) -> None:
    state = random_sb3_state_dict(3, 1, [16], seed=4)
    tensors, manifest = from_sb3_state_dict(
        state, name="scaled", domain="pendulum", action_low=[-2.0], action_high=[2.0], gamma=0.98
    )
    path = tmp_path / "scaled.safetensors"
    write_bundle(path, tensors, manifest)
    assert value_scale_main([str(path), "--v-pi", "-150.5", "--v-rand", "-600"]) == 0
    assert value_scale_main([str(path), "--v-pi", "-140", "--v-rand", "-610.25"]) == 0
    out = subprocess.run([prac_bin(), "inspect", str(path), "--json"], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout)["value_scale"] == {"v_pi": -140.0, "v_rand": -610.25}
    after, _ = read_bundle(path)
    assert sorted(after) == sorted(tensors)
    assert all(np.array_equal(after[k], tensors[k]) for k in tensors)
    with pytest.raises(SystemExit, match="is not above V_rand"):
        value_scale_main([str(path), "--v-pi", "-700", "--v-rand", "-600"])
    with pytest.raises(SystemExit):
        value_scale_main([str(path), "--v-pi", "1"])


def test_the_discounted_values_are_measured_on_the_same_seeds() -> None:
    gymnasium = pytest.importorskip("gymnasium")
    env = gymnasium.make("Pendulum-v1")
    # Pushing with the angular velocity swings it; both values are deterministic per seed.
    act = lambda obs: np.clip([2.0 * np.sign(obs[2])], -2.0, 2.0)  # noqa: E731
    first = measure(env, act, 0.98, 3, seed=10)
    assert first == measure(env, act, 0.98, 3, seed=10)
    assert first != measure(env, act, 0.98, 3, seed=11)
    expected_pi = np.mean([discounted_return(env, act, 0.98, 10 + k) for k in range(3)])
    assert first[0] == pytest.approx(expected_pi)
    with pytest.raises(ValueError, match="episodes is 0"):
        measure(env, act, 0.98, 0, seed=0)


class RunningMeanStd:
    """Pickled as SB3's: the reader turns any class it names into a holder of its attributes."""

    def __init__(self, mean: list[float], var: list[float]) -> None:
        self.mean, self.var, self.count = np.asarray(mean), np.asarray(var), 1000.0


class VecNormalize:
    def __init__(self, **fields: object) -> None:
        self.__dict__.update(fields)


class Evil:
    def __reduce__(self) -> tuple[object, tuple[str]]:
        import os

        return (os.system, ("echo pwned",))


def test_vecnormalize_statistics_are_read_without_running_the_pickle(tmp_path: pathlib.Path) -> None:
    import pickle

    from prac_client import vecnormalize

    stats_file = tmp_path / "agent" / "vecnormalize.pkl"
    stats_file.parent.mkdir()
    normalizer = VecNormalize(
        obs_rms=RunningMeanStd([0.5, -1.0, 2.0], [4.0, 0.25, 0.0]),
        clip_obs=3.0,
        epsilon=1e-8,
        norm_obs=True,
        norm_reward=False,
        gamma=0.99,
    )
    stats_file.write_bytes(pickle.dumps(normalizer))
    stats = vecnormalize.read(stats_file)
    assert (stats.norm_obs, stats.norm_reward, stats.clip_obs) == (True, False, 3.0)
    np.testing.assert_allclose(stats.normalize([2.5, -1.25, 0.001]), [1.0, -0.5, -3.0], rtol=1e-6)
    assert stats.bundle_field() == {"mean": [0.5, -1.0, 2.0], "var": [4.0, 0.25, 0.0], "clip_obs": 3.0, "epsilon": 1e-8}
    # Found beside the zip, or in ENV_ID/ beside ENV_ID.zip as the rl-zoo keeps it.
    assert vecnormalize.find(tmp_path / "agent" / "model.zip") == stats_file
    assert vecnormalize.find(tmp_path / "agent.zip") == stats_file
    assert vecnormalize.find(tmp_path / "other.zip") is None
    # A pickle that would run a command is refused; so is anything that is not a VecNormalize.
    evil = tmp_path / "evil.pkl"
    evil.write_bytes(pickle.dumps(Evil()))
    with pytest.raises(ValueError, match=r"not a readable VecNormalize file \(refuses posix.system\)"):
        vecnormalize.read(evil)
    (tmp_path / "list.pkl").write_bytes(pickle.dumps([1, 2]))
    with pytest.raises(ValueError, match="not a VecNormalize file"):
        vecnormalize.read(tmp_path / "list.pkl")
    (tmp_path / "short.pkl").write_bytes(pickle.dumps(normalizer)[:20])
    with pytest.raises(ValueError, match="not a readable VecNormalize file"):
        vecnormalize.read(tmp_path / "short.pkl")


def test_an_obs_normalization_makes_a_format_2_bundle_the_server_checks(tmp_path: pathlib.Path) -> None:
    state = random_sb3_state_dict(3, 1, [16], seed=2)
    common = dict(name="n", domain="pendulum", action_low=[-2.0], action_high=[2.0], gamma=0.99,
                  model=random_model(3, 1, [8], seed=1))
    tensors, manifest = from_sb3_state_dict(
        state, obs_normalization={"mean": [0, 0, 0], "var": [1, 1, 1], "clip_obs": 10, "epsilon": 1e-8}, **common
    )
    assert manifest["format_version"] == 2
    write_bundle(tmp_path / "n.safetensors", tensors, manifest)
    # A variance the server cannot use is refused at load, with the field named.
    tensors, manifest = from_sb3_state_dict(
        state, obs_normalization={"mean": [0, 0, 0], "var": [1, -1, 1], "clip_obs": 10, "epsilon": 1e-8}, **common
    )
    write_bundle(tmp_path / "bad.safetensors", tensors, manifest)
    result = subprocess.run(
        [prac_bin(), "inspect", str(tmp_path / "bad.safetensors")], capture_output=True, text=True, timeout=60
    )
    assert result.returncode != 0
    assert "obs_normalization.var[1]: is -1, a variance must be >= 0" in result.stderr + result.stdout


def test_the_observation_space_becomes_the_bundles_obs_bounds() -> None:
    facts = spaces_from_sb3_data(SB3_DATA)
    np.testing.assert_array_equal(facts["obs_low"], [-1.0, -1.0, -8.0])
    np.testing.assert_array_equal(facts["obs_high"], [1.0, 1.0, 8.0])
    state = random_sb3_state_dict(3, 1, [8], seed=0)
    common = {"name": "p", "domain": "pendulum", "action_low": [-2.0], "action_high": [2.0], "gamma": 0.98}
    _, manifest = from_sb3_state_dict(state, **common, obs_bounds=([-1.0, -np.inf, -8.0], [1.0, np.inf, np.inf]))
    assert manifest["format_version"] == 4
    assert manifest["obs_bounds"] == {"low": [-1.0, None, -8.0], "high": [1.0, None, None]}
    # Unbounded everywhere (a MuJoCo task's Box(-inf, inf)): no bounds, and the version stays.
    _, unbounded = from_sb3_state_dict(state, **common, obs_bounds=([-np.inf] * 3, [np.inf] * 3))
    assert "obs_bounds" not in unbounded and unbounded["format_version"] == 1
    no_space = json.loads(json.dumps(SB3_DATA))
    del no_space["observation_space"]["low"], no_space["observation_space"]["high"]
    assert spaces_from_sb3_data(no_space)["obs_low"] is None
