"""Benchmark tools: meshes and rays, stress scenes, ray recording, the traversal and scaling benchmarks,
BENCHMARKS.md."""
