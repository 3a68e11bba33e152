"""What every implementation of svox2's RMSProp rule shares (the Warp kernels of
kernels/rmsprop_kernel.py and their PyTorch oracle), kept apart so that neither imports the other."""

MEAN_SQUARE_FLOOR = 1.1754944e-38
"""The smallest normal float32: where a positive mean square's decay stops, in every implementation of
the rule (dense, owed, the PyTorch oracle), with or without subnormals flushed. It must not reach 0: the
row would read as fresh (`v <- g^2`) and take a first step 4.5x smaller (at beta 0.95) than from the
decayed state; and below it every product is subnormal, many times slower on x86 (JOURNAL.md,
"Why that pass is slow here: frozen subnormal SH")."""
