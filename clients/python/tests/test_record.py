"""python -m prac_client.record with a served policy."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys

import numpy as np
from safetensors.numpy import load_file

from conftest import Server


def test_record_writes_transitions_from_a_served_policy(server: Server, tmp_path: pathlib.Path) -> None:
    out = tmp_path / "transitions.safetensors"
    done = subprocess.run(
        [sys.executable, "-m", "prac_client.record", "--env", "Pendulum-v1", "--episodes", "2",
         "--server", server.address, "--policy", "pendulum", "--out", str(out)],
        capture_output=True, text=True, check=True,
    )
    summary = json.loads(done.stdout)
    assert (summary["transitions"], summary["episodes"], summary["seed"]) == (400, 2, 0)
    data = load_file(str(out))
    # The summary's returns are the recorded episodes' reward sums.
    returns = [data["reward"][:200].sum(), data["reward"][200:].sum()]
    assert abs(summary["return_mean"] - np.mean(returns)) < 1e-3, summary
    # What the server committed to, as it reported it (at least the action executed now).
    assert summary["forecast_mean"] >= 1 and summary["f_t_mean"] >= 1, summary
    assert data["obs"].shape == (400, 3) and data["next_obs"].shape == (400, 3)
    assert data["action"].shape == (400, 1) and data["reward"].shape == (400,)
    assert np.all(np.abs(data["action"]) <= 2.0)
    # Transitions chain within an episode: each next_obs is the following obs.
    np.testing.assert_array_equal(data["next_obs"][:199], data["obs"][1:200])


def test_record_counts_steps_and_flags_what_it_randomised(server: Server, tmp_path: pathlib.Path) -> None:
    for noise, out in (("0", tmp_path / "uniform.safetensors"), ("0.1", tmp_path / "noisy.safetensors")):
        done = subprocess.run(
            [sys.executable, "-m", "prac_client.record", "--env", "Pendulum-v1", "--steps", "450",
             "--random-fraction", "0.3", "--action-noise", noise, "--seed", "4",
             "--server", server.address, "--policy", "pendulum", "--out", str(out)],
            capture_output=True, text=True, check=True,
        )
        summary = json.loads(done.stdout)
        data = load_file(str(out))
        # 450 transitions: two full episodes and a third cut short.
        assert (summary["transitions"], summary["episodes"]) == (450, 3), summary
        assert data["explore"].shape == (450,) and set(np.unique(data["explore"])) <= {0.0, 1.0}
        assert summary["exploratory"] == int(data["explore"].sum())
        assert 90 <= summary["exploratory"] <= 180, summary
        # Only the two whole episodes count towards the return.
        whole = [data["reward"][:200].sum(), data["reward"][200:400].sum()]
        assert abs(summary["return_mean"] - np.mean(whole)) < 1e-3, summary
        assert np.all(np.abs(data["action"]) <= 2.0)
    # The same seed randomises the same steps, whichever way it randomises them.
    uniform, noisy = load_file(str(tmp_path / "uniform.safetensors")), load_file(str(tmp_path / "noisy.safetensors"))
    np.testing.assert_array_equal(uniform["explore"][:200], noisy["explore"][:200])
    bad = subprocess.run(
        [sys.executable, "-m", "prac_client.record", "--env", "Pendulum-v1", "--steps", "10", "--random-fraction", "2",
         "--server", server.address, "--policy", "pendulum", "--out", str(tmp_path / "x")],
        capture_output=True, text=True,
    )
    assert bad.returncode == 2 and "random fraction 2.0; expected 0..1" in bad.stderr
