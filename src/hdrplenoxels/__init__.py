"""hdrplenoxels: HDR radiance fields (Plenoxels + learned tone mapping) from photos with varying settings."""

__version__ = "0.1.0"
