"""SB3's VecNormalize statistics (`vecnormalize.pkl`), read without SB3 and without running any
code from the pickle.

An agent trained behind VecNormalize acts on `clip((s - mean) / sqrt(var + epsilon), +-clip_obs)`;
its bundle carries those numbers as `obs_normalization` and the server applies them in front of
the actor and critics. The pickle is read with an unpickler that builds numpy arrays and plain
attribute holders only: every other name it meets (VecNormalize, RunningMeanStd, the spaces) is
replaced by a holder of its attributes, never called as what it names, and names from os,
subprocess, builtins and the like are refused outright.
"""

from __future__ import annotations

import dataclasses
import pathlib
import pickle
from typing import Any

import numpy as np
import numpy.typing as npt

FILE_NAME = "vecnormalize.pkl"

# What numpy needs to rebuild arrays, dtypes and scalars; nothing else of numpy is called.
_NUMPY = {
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
}
_SAFE = {("collections", "OrderedDict"), ("copyreg", "_reconstructor"), ("builtins", "object")}
_SAFE.update(("builtins", t) for t in ("dict", "list", "tuple", "set", "frozenset", "float", "int", "bool", "str", "bytes"))


@dataclasses.dataclass
class Stats:
    """The parts of a VecNormalize that decide what the agent saw."""

    norm_obs: bool
    norm_reward: bool
    mean: npt.NDArray[np.float64]
    var: npt.NDArray[np.float64]
    clip_obs: float
    epsilon: float

    def normalize(self, obs: npt.ArrayLike) -> npt.NDArray[np.float32]:
        """The observation as the agent saw it (VecNormalize.normalize_obs)."""
        obs = np.asarray(obs, dtype=np.float64)
        if not self.norm_obs:
            return obs.astype(np.float32)
        scaled = np.clip((obs - self.mean) / np.sqrt(self.var + self.epsilon), -self.clip_obs, self.clip_obs)
        return scaled.astype(np.float32)

    def bundle_field(self) -> dict[str, Any] | None:
        """The manifest's `obs_normalization`, or None where observations were not normalised."""
        if not self.norm_obs:
            return None
        return {
            "mean": [float(v) for v in self.mean],
            "var": [float(v) for v in self.var],
            "clip_obs": float(self.clip_obs),
            "epsilon": float(self.epsilon),
        }


class _Holder:
    """Stands in for any class the pickle names: keeps the attributes it is given."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        # A dict of attributes, a (dict, slots) pair, or what an extension type keeps (ignored).
        for part in state if isinstance(state, tuple) else (state,):
            if isinstance(part, dict):
                self.__dict__.update({k: v for k, v in part.items() if isinstance(k, str)})


class _Unpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _NUMPY or (module, name) in _SAFE:
            return super().find_class(module, name)
        if module.split(".")[0] in ("builtins", "os", "posix", "subprocess", "sys", "importlib", "runpy", "pickle", "io", "shutil", "socket"):
            raise pickle.UnpicklingError(f"refuses {module}.{name}")
        # Classes of SB3, gym or gymnasium (and numpy's random generators inside spaces): holders.
        return type(name, (_Holder,), {"__module__": "prac_client.vecnormalize.held"})


def find(checkpoint: str | pathlib.Path) -> pathlib.Path | None:
    """The VecNormalize file of an SB3 checkpoint: beside it, or where the rl-zoo keeps it
    (ENV_ID/vecnormalize.pkl beside ENV_ID.zip)."""
    checkpoint = pathlib.Path(checkpoint)
    stem = checkpoint.name[:-4] if checkpoint.name.endswith(".zip") else checkpoint.name
    for candidate in (checkpoint.parent / FILE_NAME, checkpoint.parent / stem / FILE_NAME):
        if candidate.is_file():
            return candidate
    return None


def read(path: str | pathlib.Path) -> Stats:
    """The statistics of a VecNormalize saved by SB3 (`VecNormalize.save`, the rl-zoo's
    vecnormalize.pkl); anything else is a ValueError with one line."""
    try:
        with open(path, "rb") as f:
            loaded = _Unpickler(f).load()
    except Exception as e:  # a malformed pickle can fail in any of pickle's, numpy's or our ways
        raise ValueError(f"{path}: not a readable VecNormalize file ({e})") from None
    fields = getattr(loaded, "__dict__", {})
    missing = [f for f in ("obs_rms", "clip_obs", "epsilon") if f not in fields]
    if missing:
        raise ValueError(f"{path}: not a VecNormalize file (no {', '.join(missing)})")
    obs_rms = fields["obs_rms"]
    if isinstance(obs_rms, dict):
        raise ValueError(f"{path}: normalises a Dict observation space; prac bundles take flat observations")
    mean = np.asarray(getattr(obs_rms, "mean", None), dtype=np.float64)
    var = np.asarray(getattr(obs_rms, "var", None), dtype=np.float64)
    if mean.ndim != 1 or mean.shape != var.shape:
        raise ValueError(f"{path}: obs_rms mean {mean.shape} and var {var.shape} are not one flat observation")
    return Stats(
        norm_obs=bool(fields.get("norm_obs", True)),
        norm_reward=bool(fields.get("norm_reward", False)),
        mean=mean,
        var=var,
        clip_obs=float(fields["clip_obs"]),
        epsilon=float(fields["epsilon"]),
    )


def for_checkpoint(checkpoint: str | pathlib.Path, given: str | None = None) -> tuple[pathlib.Path | None, Stats | None]:
    """The VecNormalize file of a checkpoint (`given`, or the one `find` finds) and its
    statistics; (None, None) where it has none. An unreadable file ends the command in one line."""
    path = pathlib.Path(given) if given else find(checkpoint)
    if path is None:
        return None, None
    try:
        return path, read(path)
    except ValueError as e:
        raise SystemExit(str(e)) from None


NORMALISED_REWARDS = (
    "the agent was trained on normalised rewards, so its Q is not in the env's return units and a "
    "value scale would misstate epsilon_coef; give absolute epsilons (in Q's units) instead"
)
