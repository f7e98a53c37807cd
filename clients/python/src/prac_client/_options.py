"""Session options as keyword arguments -> prac.v1.SessionOptions."""

from __future__ import annotations

from prac_client._proto.prac.v1 import prac_pb2 as pb

Growth = str | tuple[str, int]


def session_options(
    *,
    epsilon: float | None,
    epsilon_coef: float | None,
    growth: Growth | None,
    max_horizon: int | None,
    seed: int | None,
    sampled: bool | None,
    every_critic: bool = False,
    support_limit: float | None = None,
    max_epsilon_coef: float | None = None,
) -> pb.SessionOptions:
    """`growth` is ("grow", k) / ("fixed", n) or "grow 2" / "fixed:8". A seed implies sampled.
    every_critic, support_limit and max_epsilon_coef set the guard (prac.v1.PlanGuard); without
    them the policy's default_guard."""
    options = pb.SessionOptions()
    if epsilon is not None and epsilon_coef is not None:
        raise ValueError("give epsilon or epsilon_coef, not both")
    if epsilon is not None:
        options.epsilon = float(epsilon)
    if epsilon_coef is not None:
        options.epsilon_coef = float(epsilon_coef)
    if growth is not None:
        mode, n = _parse_growth(growth)
        if mode == "grow":
            options.grow = n
        else:
            options.fixed = n
    if max_horizon is not None:
        if max_horizon < 1:
            raise ValueError(f"max_horizon must be >= 1, got {max_horizon}")
        options.max_horizon = max_horizon
    options.sampled = bool(sampled) if sampled is not None else seed is not None
    if seed is not None:
        options.seed = seed
    if every_critic or support_limit is not None or max_epsilon_coef is not None:
        if support_limit is not None and not support_limit >= 0:
            raise ValueError(f"support_limit must be >= 0, got {support_limit}")
        if max_epsilon_coef is not None and not max_epsilon_coef >= 0:
            raise ValueError(f"max_epsilon_coef must be >= 0, got {max_epsilon_coef}")
        options.guard.every_critic = bool(every_critic)
        options.guard.support_limit = float(support_limit or 0.0)
        options.guard.max_epsilon_coef = float(max_epsilon_coef or 0.0)
    return options


def _parse_growth(growth: Growth) -> tuple[str, int]:
    if isinstance(growth, str):
        parts = growth.replace(":", " ").split()
        if len(parts) != 2 or not parts[1].isdigit():
            raise ValueError(f"growth {growth!r}: expected 'grow K' or 'fixed N'")
        mode, n = parts[0], int(parts[1])
    else:
        mode, n = growth
    if mode not in ("grow", "fixed"):
        raise ValueError(f"growth mode {mode!r}: expected 'grow' or 'fixed'")
    if n < 1:
        raise ValueError(f"growth {mode} {n}: expected a count >= 1")
    return mode, int(n)
