"""The committed gRPC stubs are what generate_stubs.py makes from proto/ now."""

from __future__ import annotations

import pathlib
import sys

HERE = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(HERE))

from generate_stubs import PACKAGE_PREFIX, generate  # noqa: E402


def test_committed_stubs_are_up_to_date(tmp_path: pathlib.Path) -> None:
    fresh = generate(tmp_path)
    committed_root = HERE / "src"
    for path in fresh:
        relative = path.relative_to(tmp_path)
        committed = committed_root / relative
        assert committed.exists(), f"{relative} is not committed: run python generate_stubs.py"
        assert committed.read_bytes() == path.read_bytes(), f"{relative} is stale: run python generate_stubs.py"
    generated = {p.relative_to(tmp_path) for p in fresh}
    package = committed_root / PACKAGE_PREFIX
    stale = {
        p.relative_to(committed_root)
        for p in package.rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    } - generated
    assert not stale, f"{sorted(map(str, stale))} are not generated any more: remove them"
    # The service's types, for sync and asyncio channels alike.
    assert pathlib.Path(PACKAGE_PREFIX, "prac/v1/prac_pb2_grpc.pyi") in generated
