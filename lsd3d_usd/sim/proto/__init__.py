"""The service of `lsd3d-usd sim serve` (sim.proto) and its Python stubs.

sim_pb2.py and sim_pb2_grpc.py are generated (grpcio-tools 1.85.4), never edited; after a
change to sim.proto, from the repository root:
    python -m grpc_tools.protoc -I . --python_out=. --grpc_python_out=. lsd3d_usd/sim/proto/sim.proto
"""
