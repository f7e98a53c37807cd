"""Link loss on a robot, measured: episodes of one of prac's robots (`prac/<Domain>-v0`) played
uninterrupted, then again with every server lost at step --at and one back at step --back, the
session going on on board (`fallback=`, `prac export-onnx`'s files under ONNX Runtime) between.

    PRAC_BIN=target/release/prac python clients/python/fallback_proof.py --domain hopper \\
        --episodes 1 --cut kill --at 100 --back 600 [--json results/fallback/hopper-kill.json]

--cut kill SIGKILLs the server and starts a new one on the same address; --cut proxy leaves the
server running and has the proxy in between stop forwarding (the connections stay open, silent)
and, at --back, drop its old connections and forward new ones. --back -1: never back (every step
from --at on is on board, which times the on-board Replan). Prints, per episode, the return and
steps of both runs, whether either fell, the local steps, whether the steps were contiguous, and
whether the server's plan after the return kept the local plan's commitment.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import select
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

import prac_client.envs  # noqa: F401  (registers prac/<Domain>-v0)
from prac_client import Client
from prac_client.onboard import Fallback
from prac_client.types import StepResult

REPO = pathlib.Path(__file__).resolve().parents[2]
ENV_IDS = {domain: env_id for env_id, domain in prac_client.envs.ENVS.items()}


def prac_bin() -> str:
    return os.environ.get("PRAC_BIN", str(REPO / "target" / "release" / "prac"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Server:
    """`prac serve` on a fixed address, so that a restarted one is found where the first was."""

    def __init__(self, bundles: pathlib.Path, address: str) -> None:
        self.process = subprocess.Popen(
            [prac_bin(), "serve", "--listen", address, "--bundles", str(bundles)],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        if not line.startswith("listening on "):
            self.process.kill()
            raise RuntimeError(f"the server did not start: {line!r}")
        deadline = time.monotonic() + 30
        with Client(address, timeout=2) as client:
            while True:
                try:
                    client.policies()
                    return
                except Exception:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.05)

    def kill(self) -> None:
        self.process.kill()
        self.process.wait(10)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(10)


class LinkProxy:
    """A TCP proxy that can stop forwarding without closing anything (a link that went silent),
    and come back with its old connections gone (a link whose flows did not survive)."""

    def __init__(self, upstream: str) -> None:
        host, port = upstream.rsplit(":", 1)
        self.upstream = (host, int(port))
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.address = "127.0.0.1:%d" % self.listener.getsockname()[1]
        self.silent = False
        self.lock = threading.Lock()
        self.open: list[socket.socket] = []
        self.closed = False
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self.closed:
            try:
                downstream, _ = self.listener.accept()
            except OSError:
                return
            with self.lock:
                self.open.append(downstream)
                if self.silent:
                    continue  # held open, never answered
            try:
                upstream = socket.create_connection(self.upstream)
            except OSError:
                downstream.close()
                continue
            with self.lock:
                self.open.append(upstream)
            for a, b in ((downstream, upstream), (upstream, downstream)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket) -> None:
        try:
            while not self.closed:
                if self.silent:
                    time.sleep(0.005)
                    continue
                ready, _, _ = select.select([source], [], [], 0.05)
                if not ready or self.silent:
                    continue
                data = source.recv(65536)
                if not data:
                    break
                sink.sendall(data)
        except (OSError, ValueError):  # closed by restore()
            pass
        for s in (source, sink):
            try:
                s.close()
            except OSError:
                pass

    def cut(self) -> None:
        self.silent = True

    def restore(self) -> None:
        with self.lock:
            for s in self.open:
                try:
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
                    s.close()  # a reset: the old flows are gone
                except OSError:
                    pass
            self.open.clear()
            self.silent = False

    def close(self) -> None:
        self.closed = True
        self.listener.close()
        self.restore()


@dataclass
class Episode:
    seed: int
    steps: int
    episode_return: float
    fell: bool
    local_steps: int = 0
    contiguous: bool = True
    # The first served answer after the local steps: how many of the local plan's actions it kept,
    # and whether those are the local plan's (same actions, same decision steps).
    kept_after_return: int | None = None
    continues_local_plan: bool | None = None
    local_step_us: list[float] = field(default_factory=list)


def play(
    client: Client,
    policy: str,
    env: Any,
    seed: int,
    *,
    epsilon_coef: float,
    fallback: Fallback | None = None,
    at: int | None = None,
    back: int | None = None,
    lose: Any = None,
    regain: Any = None,
) -> Episode:
    """One episode; with `lose` and `regain`, called before steps `at` and `back`."""
    session = client.session(policy, epsilon_coef=epsilon_coef, fallback=fallback)
    session.probe_every = 0.05
    observation, _ = env.reset(seed=seed)
    total, t = 0.0, 0
    terminated = truncated = False
    previous: StepResult | None = None
    episode = Episode(seed=seed, steps=0, episode_return=0.0, fell=False)
    while True:
        if t == at and lose is not None:
            lose()
        if t == back and regain is not None:
            regain()
        start = time.perf_counter()
        result = session.step(observation, new_episode=t == 0)
        elapsed = time.perf_counter() - start
        if result.local:
            episode.local_step_us.append(elapsed * 1e6)
        episode.contiguous &= result.step == t and result.episode == 0
        if previous is not None and previous.local and not result.local and episode.kept_after_return is None:
            kept = result.kept
            episode.kept_after_return = kept
            episode.continues_local_plan = bool(
                np.array_equal(result.decided_at[:kept], previous.decided_at[1 : 1 + kept])
                and np.allclose(result.forecast_actions[:kept], previous.forecast_actions[1 : 1 + kept], atol=1e-5)
            )
        previous = result
        observation, reward, terminated, truncated, _ = env.step(result.action)
        total += float(reward)
        t += 1
        if terminated or truncated:
            break
    episode.steps, episode.episode_return, episode.fell = t, total, bool(terminated)
    episode.local_steps = session.local_steps
    try:
        session.close()
    except Exception:
        pass  # the session may live on a server that is gone
    return episode


def export(bundle: pathlib.Path, out: pathlib.Path) -> None:
    subprocess.run([prac_bin(), "export-onnx", str(bundle), "--out", str(out)], check=True, stdout=subprocess.DEVNULL)


def run(domain: str, episodes: int, cut: str, at: int, back: int, epsilon_coef: float, seed: int = 0) -> list[tuple[Episode, Episode]]:
    """(uninterrupted, interrupted) per episode."""
    bundle = REPO / "bundles" / f"{domain}.safetensors"
    with tempfile.TemporaryDirectory() as tmp:
        folder = pathlib.Path(tmp)
        bundles = folder / "bundles"
        bundles.mkdir()
        (bundles / bundle.name).symlink_to(bundle)
        export(bundle, folder / "onnx")
        fallback = Fallback(folder / "onnx")
        address = f"127.0.0.1:{free_port()}"
        server = Server(bundles, address)
        proxy = LinkProxy(address) if cut == "proxy" else None
        target = proxy.address if proxy is not None else address
        env = gym.make(ENV_IDS[domain])
        pairs = []
        try:
            for k in range(episodes):
                with Client(target, timeout=10) as client:
                    reference = play(client, domain, env, seed + k, epsilon_coef=epsilon_coef)

                def lose() -> None:
                    nonlocal server
                    if proxy is not None:
                        proxy.cut()
                    else:
                        server.kill()

                def regain() -> None:
                    nonlocal server
                    if proxy is not None:
                        proxy.restore()
                    else:
                        server = Server(bundles, address)

                with Client(target, timeout=0.25, patience=0.1) as client:
                    interrupted = play(
                        client,
                        domain,
                        env,
                        seed + k,
                        epsilon_coef=epsilon_coef,
                        fallback=fallback,
                        at=at,
                        back=back if back >= 0 else None,
                        lose=lose,
                        regain=regain,
                    )
                if back < 0 or interrupted.steps <= back:
                    regain()
                pairs.append((reference, interrupted))
        finally:
            env.close()
            if proxy is not None:
                proxy.close()
            server.stop()
    return pairs


def summary(pairs: list[tuple[Episode, Episode]]) -> dict[str, Any]:
    local = [us for _, e in pairs for us in e.local_step_us]
    return {
        "episodes": len(pairs),
        "falls_uninterrupted": sum(r.fell for r, _ in pairs),
        "falls_interrupted": sum(e.fell for _, e in pairs),
        "largest_return_difference": max(abs(e.episode_return - r.episode_return) / max(abs(r.episode_return), 1e-9) for r, e in pairs),
        "local_steps": sum(e.local_steps for _, e in pairs),
        "all_contiguous": all(e.contiguous for _, e in pairs),
        "all_continue_local_plan": all(e.continues_local_plan is not False for _, e in pairs),
        "local_step_us": {
            "mean": float(np.mean(local)) if local else None,
            "p50": float(np.percentile(local, 50)) if local else None,
            "p99": float(np.percentile(local, 99)) if local else None,
        },
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--domain", required=True, choices=sorted(ENV_IDS))
    parser.add_argument("--episodes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cut", choices=["kill", "proxy"], default="kill")
    parser.add_argument("--at", type=int, default=100)
    parser.add_argument("--back", type=int, default=600)
    parser.add_argument("--epsilon-coef", type=float, default=0.005)
    parser.add_argument("--json", type=pathlib.Path, help="write the episodes and the summary here")
    args = parser.parse_args(argv)
    pairs = run(args.domain, args.episodes, args.cut, args.at, args.back, args.epsilon_coef, args.seed)
    for reference, interrupted in pairs:
        print(
            f"seed {reference.seed}: uninterrupted {reference.episode_return:.1f} in {reference.steps} steps"
            f"{' (fell)' if reference.fell else ''}; interrupted {interrupted.episode_return:.1f} in "
            f"{interrupted.steps} steps{' (fell)' if interrupted.fell else ''}, {interrupted.local_steps} on board, "
            f"contiguous {interrupted.contiguous}, kept after the return {interrupted.kept_after_return} "
            f"(continues the local plan: {interrupted.continues_local_plan})"
        )
    result = summary(pairs)
    print(json.dumps(result, indent=2))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), "unknown")
        record = {
            "command": " ".join(["python", "clients/python/fallback_proof.py", *(argv or sys.argv[1:])]),
            "cpu": cpu,
            "summary": result,
            "episodes": [
                {"uninterrupted": asdict(r), "interrupted": {**asdict(e), "local_step_us": None}} for r, e in pairs
            ],
        }
        args.json.write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
