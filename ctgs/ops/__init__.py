"""Compiled operations: the C++/CUDA extension's just-in-time build (ext, ext_cuda), the dense fused CPU
passes of the model and the training loop (fused), and the choice of compiled kernel for a tensor's device
(dispatch). Everything here falls back to nothing above it: callers use PyTorch where an op does not apply."""
