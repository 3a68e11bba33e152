"""Where an operation's implementation is chosen: its Warp kernel or its PyTorch reference
(`kernels.dispatch`; docs/design.md, "Kernels")."""
