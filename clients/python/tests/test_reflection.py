"""Server reflection as grpcio's own reflection client reads it (it speaks v1alpha)."""

from __future__ import annotations

import grpc
from google.protobuf.descriptor_pool import DescriptorPool
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

from conftest import Server


def test_grpcio_reflection_lists_and_describes_the_services(server: Server) -> None:
    with grpc.insecure_channel(server.address) as channel:
        database = ProtoReflectionDescriptorDatabase(channel)
        services = set(database.get_services())
        assert {"prac.v1.Prac", "grpc.health.v1.Health"} <= services, services
        pool = DescriptorPool(database)
        prac = pool.FindServiceByName("prac.v1.Prac")
        assert {"OpenSession", "StepStream", "GetPlan"} <= {m.name for m in prac.methods}
        step = pool.FindMessageTypeByName("prac.v1.StepRequest")
        assert "observation" in step.fields_by_name
        health = pool.FindServiceByName("grpc.health.v1.Health")
        assert {"Check", "Watch"} <= {m.name for m in health.methods}
