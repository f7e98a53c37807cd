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
from prac_client import Client
from prac_client.bundle import from_sb3_state_dict, random_model, random_sb3_state_dict, write_bundle
from prac_client.export_sb3 import main as export_main
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
