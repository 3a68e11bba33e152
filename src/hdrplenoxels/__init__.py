"""hdrplenoxels: HDR radiance fields (Plenoxels + learned tone mapping) from photos with varying settings.

Importing the package changes nothing in the process. For the CPU speed settings the command line uses,
call `hdrplenoxels.core.process_settings.apply_process_settings()` before importing torch.
"""

__version__ = "0.1.0"
