"""The interactive HDR viewer (`hdrplenoxels view`): viser in the browser, rendering with the package's own
renderer; docs/design.md, "Viewer"."""
