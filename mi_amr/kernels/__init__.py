"""The Dr.Jit kernels: device arrays, reconstruction, roots of cubics, kd-tree traversal, the
surface and volume methods, colour maps and the opacity band; generic over a JIT backend."""
