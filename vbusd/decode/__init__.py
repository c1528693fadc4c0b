"""Decoders: the numpy reference, the warp kernels (CPU and CUDA), the reference shaders and the
USD point cache built from them."""
