"""Regenerates the committed gRPC stubs in src/prac_client/_proto from ../../proto.

Run with the pinned grpcio-tools and mypy-protobuf (pip install -e '.[dev]'): python generate_stubs.py
tests/test_stubs.py fails when the committed stubs differ from what this writes.

grpcio-tools writes the modules and the messages' types (prac_pb2.pyi); mypy-protobuf's
protoc-gen-mypy_grpc writes the service's (prac_pb2_grpc.pyi), which type each RPC's request
and response for grpc.Channel and grpc.aio.Channel alike.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import sys

HERE = pathlib.Path(__file__).resolve().parent
PROTO_ROOT = HERE.parent.parent / "proto"
PROTO = "prac/v1/prac.proto"
# The generated modules import each other as prac_client._proto.prac.v1.*.
PACKAGE_PREFIX = "prac_client/_proto"
GRPC_TYPES_PLUGIN = "protoc-gen-mypy_grpc"


def grpc_types_plugin() -> str:
    """mypy-protobuf's plugin: beside this Python (a virtualenv's bin/) or on PATH."""
    search = os.pathsep.join([str(pathlib.Path(sys.executable).parent), os.environ.get("PATH", "")])
    found = shutil.which(GRPC_TYPES_PLUGIN, path=search)
    if found is None:
        raise RuntimeError(f"{GRPC_TYPES_PLUGIN} not found: pip install -e '.[dev]' (mypy-protobuf)")
    return found


def generate(out_root: pathlib.Path) -> list[pathlib.Path]:
    """Writes the stubs under out_root/prac_client/_proto and returns the files written."""
    from grpc_tools import protoc

    include = pathlib.Path(protoc.__file__).parent / "_proto"
    out_root.mkdir(parents=True, exist_ok=True)
    args = [
        "grpc_tools.protoc",
        f"-I{PACKAGE_PREFIX}={PROTO_ROOT}",
        f"-I{include}",
        f"--python_out={out_root}",
        f"--pyi_out={out_root}",
        f"--grpc_python_out={out_root}",
        f"--plugin={GRPC_TYPES_PLUGIN}={grpc_types_plugin()}",
        f"--mypy_grpc_out=quiet:{out_root}",
        f"{PACKAGE_PREFIX}/{PROTO}",
    ]
    if protoc.main(args) != 0:
        raise RuntimeError(f"protoc failed: {' '.join(args)}")
    package = out_root / PACKAGE_PREFIX
    for folder in [package, package / "prac", package / "prac" / "v1"]:
        (folder / "__init__.py").touch()
    return sorted(p for p in package.rglob("*") if p.is_file() and "__pycache__" not in p.parts)


if __name__ == "__main__":
    for path in generate(HERE / "src"):
        print(path.relative_to(HERE))
    sys.exit(0)
