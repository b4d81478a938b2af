"""Benchmark-only code: throughput measurements and the reference renderers and networks
they compare against (MuJoCo's OpenGL renderer, the network in PyTorch)."""
