"""hdrplenoxels: HDR radiance fields (Plenoxels + learned tone mapping) from photos with varying settings."""

import os

# Our CPU kernels run on Python threads between torch ops. torch's OpenMP threads spin for a while after
# each op (GNU OpenMP: 300k spins) and take the cores those kernels need; sleeping at once (passive
# waiting) makes every small torch op pay a wake-up instead. A short spin keeps both fast: the demo
# trains in 9.9 s against 12.6 s (default) and 10.7 s (passive). Only effective when set before torch
# is imported; a user's own setting wins.
os.environ.setdefault("GOMP_SPINCOUNT", "10000")
# The ray march reads and adds into grid rows scattered over hundreds of MB; with 4 KiB pages nearly
# every row costs a TLB miss. torch's CPU allocator backs large tensors with 2 MiB pages when asked
# (where the kernel's transparent huge pages are "madvise", as on Ubuntu): the 512x512x256 benchmark
# grid trains 1.1-1.6x faster, peak memory unchanged (benchmarks/RESULTS.md). torch reads this at its
# first large CPU allocation, so importing us after torch still works if no large tensor exists yet;
# a user's own setting wins.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

__version__ = "0.1.0"
