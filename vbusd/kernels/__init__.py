"""Kernels: the conversion's hot loops as warp kernels with their numpy twins, warp set-up and core counts."""
