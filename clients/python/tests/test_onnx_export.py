"""`prac export-onnx` as a robot team uses it: ONNX Runtime runs the exported actor, critics and
dynamics model of every shipped bundle, and of an SB3-imported one, on the states in the
export's reference file, and reproduces prac's outputs there. Prints the largest difference per
network."""

from __future__ import annotations

import json
import pathlib
import subprocess
from typing import Any

import numpy as np
import pytest

from conftest import REPO, prac_bin
from prac_client.bundle import from_sb3_state_dict, random_model, random_sb3_state_dict, write_bundle

ort = pytest.importorskip("onnxruntime", reason="onnxruntime is not installed (prac-client[dev] pins it)")
from safetensors.numpy import load_file  # noqa: E402

SHIPPED = sorted((REPO / "bundles").glob("*.safetensors"))


def export(bundle: pathlib.Path, out: pathlib.Path) -> dict[str, Any]:
    subprocess.run([prac_bin(), "export-onnx", str(bundle), "--out", str(out)], check=True, capture_output=True, text=True)
    contract: dict[str, Any] = json.loads((out / "prac.json").read_text())
    return contract


def largest_difference(ours: np.ndarray, theirs: np.ndarray) -> float:
    assert ours.shape == theirs.shape, (ours.shape, theirs.shape)
    return float(np.max(np.abs(ours - theirs) / (1.0 + np.abs(ours))))


def check(bundle: pathlib.Path, out: pathlib.Path) -> dict[str, float]:
    contract = export(bundle, out)
    reference = load_file(str(out / contract["reference"]))
    found = {}
    for file in [contract["actor"], *contract["critics"], *([contract["model"]] if contract["model"] else [])]:
        session = ort.InferenceSession(str(out / file["path"]), providers=["CPUExecutionProvider"])
        assert [i.name for i in session.get_inputs()] == file["inputs"]
        outputs = session.run(file["outputs"], {name: reference[name] for name in file["inputs"]})
        stem = file["path"].removesuffix(".onnx")
        for name, theirs in zip(file["outputs"], outputs):
            found[f"{stem}.{name}"] = largest_difference(reference[f"{stem}.{name}"], theirs)
    for network, difference in found.items():
        print(f"{bundle.stem}: {network}: largest relative difference {difference:.2e}")
        assert difference < 1e-4, (bundle.stem, network, difference)
    return found


@pytest.mark.parametrize("bundle", SHIPPED, ids=lambda p: p.stem)
def test_onnx_runtime_reproduces_prac_on_every_shipped_bundle(bundle: pathlib.Path, tmp_path: pathlib.Path) -> None:
    found = check(bundle, tmp_path / bundle.stem)
    assert {"actor.action", "critic_0.q", "critic_1.q", "model.next_observation"} <= set(found)


def test_onnx_runtime_reproduces_prac_on_an_sb3_imported_bundle(tmp_path: pathlib.Path) -> None:
    # SB3's SAC layout, with VecNormalize's observation normalisation and a dynamics model.
    state = random_sb3_state_dict(5, 2, [64, 48], seed=11)
    tensors, manifest = from_sb3_state_dict(
        state, name="sb3", domain="toy", action_low=[-1.0, 0.0], action_high=[1.0, 4.0], gamma=0.99,
        model=random_model(5, 2, [32], seed=3),
        obs_normalization={"mean": [0.1, -0.2, 0.0, 0.3, 1.0], "var": [1.0, 4.0, 0.25, 2.0, 9.0], "clip_obs": 10.0, "epsilon": 1e-8},
        obs_bounds=([-5.0] * 5, [5.0] * 5),
    )
    bundle = tmp_path / "sb3.safetensors"
    write_bundle(bundle, tensors, manifest)
    found = check(bundle, tmp_path / "sb3")
    assert "actor.log_std" in found and "model.next_observation" in found


def test_a_truncated_bundle_is_refused_and_nothing_is_written(tmp_path: pathlib.Path) -> None:
    truncated = tmp_path / "hopper.safetensors"
    truncated.write_bytes((REPO / "bundles" / "hopper.safetensors").read_bytes()[:5000])
    out = tmp_path / "out"
    result = subprocess.run([prac_bin(), "export-onnx", str(truncated), "--out", str(out)], capture_output=True, text=True)
    assert result.returncode != 0 and "cannot export" in result.stderr, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hopper.safetensors"]
