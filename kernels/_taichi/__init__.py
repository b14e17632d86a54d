"""Taichi implementations of swarmsplat's kernels. Private: import through `kernels`, after `kernels.use()`."""
