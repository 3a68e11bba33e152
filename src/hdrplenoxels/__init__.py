"""hdrplenoxels: HDR radiance fields (Plenoxels + learned tone mapping) from photos with varying settings."""

import os

# Our CPU kernels run on Python threads between torch ops. With OpenMP's default (spinning) wait policy
# torch's idle worker threads keep spinning after each op and take the cores those kernels need (the
# renderer's kernels took 1.6x as long on 2 cores). Only effective when set before torch is imported;
# a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
