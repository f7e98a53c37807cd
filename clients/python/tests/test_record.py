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
    assert data["obs"].shape == (400, 3) and data["next_obs"].shape == (400, 3)
    assert data["action"].shape == (400, 1) and data["reward"].shape == (400,)
    assert np.all(np.abs(data["action"]) <= 2.0)
    # Transitions chain within an episode: each next_obs is the following obs.
    np.testing.assert_array_equal(data["next_obs"][:199], data["obs"][1:200])
