"""Decoders: the numpy reference, the warp kernels (CPU and CUDA) and the reference shaders."""
